"""How much of the goal-reaching skill can transfer from scene A to scene B at all.

    python bench/probe_transfer.py --alt 300 --regions 8 --iters 2000
    python bench/probe_transfer.py --alt 100 --regions 30 --iters 2000
    python bench/probe_transfer.py --alt 300 --regions 8 --iters 1000 --encoder corr

A supervised upper bound for zero-shot transfer. The project's own view layers (the
SmallCNN encoder, the current- and target-view embeddings and the FC layer of
:class:`geonav.policy.model.ActorCritic`, with its input scaling and initialisation; no
LSTM, since one view pair fixes the answer) are trained by full supervision on the
shortest-path action for every (current cell, target cell) pair of ``--regions`` 140 m
meta-task regions of scene A (7 x 7 cells of 20 m). The loss is the log-probability of the
set of actions that shorten the path (one or two of four). It prints the fraction of pairs
whose argmax action shortens the path on the training pairs, on held-out regions of scene
A and on regions of scene B, beside chance: a uniform random action, and the best action
that ignores the views (always the majority-good action).

An RL learner sees far less supervision than this, so the scene-B figure bounds what
meta-training on A can give a policy on B before fine-tuning (docs/learning.md §6).
``--encoder corr`` puts the frozen correlation encoder (each view's normalised
cross-correlation with the target view, ``NetConfig(encoder='corr')``) in front of the
same embeddings and FC layer instead of the trainable CNN (docs/learning.md §8).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from geonav.camera import Camera  # noqa: E402
from geonav.demo import ensure_scene  # noqa: E402
from geonav.env import GeoNavEnv  # noqa: E402
from geonav.policy.config import NetConfig  # noqa: E402
from geonav.policy.encoders import build_frozen_encoder  # noqa: E402
from geonav.policy.model import ActorCritic  # noqa: E402
from geonav.scene import Scene  # noqa: E402
from geonav.tasks import ACTION_MOVES, TaskSet, sample_meta_tasks  # noqa: E402

PX = 64


def view_table(scene: Scene, ts: TaskSet) -> list[np.ndarray]:
    """Per region: the (nx, ny, PX, PX, 3) nadir views of its cells."""
    out = []
    for t in ts.tasks:
        env = GeoNavEnv(scene, replace(ts, tasks=[t]))
        nx, ny = t.lattice.shape
        imgs = np.zeros((nx, ny, PX, PX, 3), np.uint8)
        other = (0, 0) if tuple(t.target_cell) != (0, 0) else (0, 1)
        for i in range(nx):
            for j in range(ny):
                if (i, j) == tuple(t.target_cell):  # the env never starts on its target
                    imgs[i, j] = env.reset(options={"start_cell": other})[0]["target"]
                else:
                    imgs[i, j] = env.reset(options={"start_cell": (i, j)})[0]["image"]
        out.append(imgs)
    return out


def pairs(tables: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(current view, target view, good-action mask) for every ordered cell pair."""
    cur, tgt, good = [], [], []
    for imgs in tables:
        nx, ny = imgs.shape[:2]
        flat = imgs.reshape(nx * ny, PX, PX, 3)
        for a in range(nx * ny):
            ax, ay = divmod(a, ny)
            for b in range(nx * ny):
                if a == b:
                    continue
                bx, by = divmod(b, ny)
                d = abs(ax - bx) + abs(ay - by)
                m = np.array([abs(ax + dx - bx) + abs(ay + dy - by) < d
                              for dx, dy in ACTION_MOVES])
                cur.append(flat[a])
                tgt.append(flat[b])
                good.append(m)
    return np.stack(cur), np.stack(tgt), np.stack(good)


class ViewHead(nn.Module):
    """ActorCritic's view layers (encoder, embeddings, FC) and a 4-way action head."""

    def __init__(self, seed: int, encoder: str = "cnn", corr_radius: int = 8) -> None:
        super().__init__()
        torch.manual_seed(seed)
        cfg = NetConfig(obs_size_px=PX, encoder=encoder, corr_radius=corr_radius)
        self.ac = ActorCritic(cfg)
        self.frozen = build_frozen_encoder(cfg)
        self.head = nn.Linear(self.ac.cfg.hidden_size, 4)

    def forward(self, cur: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
        ac = self.ac
        if self.frozen is not None:  # pairwise: the view against its target, the target's own
            mc, mt = self.frozen.encode(cur), self.frozen.encode(tgt)
            fc, ft = self.frozen.combine(mc, mt), self.frozen.combine(mt, mt)
        else:
            fc, ft = ac.features(cur), ac.features(tgt)
        o = F.relu(ac.obs_embed(fc))
        t = F.relu(ac.target_embed(ft))
        a = F.relu(ac.action_embed(torch.zeros(len(cur), ac.cfg.n_actions)))
        return self.head(F.relu(ac.fc(torch.cat([o, t, a], 1))))


def accuracy(net: ViewHead, cur: np.ndarray, tgt: np.ndarray, good: np.ndarray) -> float:
    with torch.no_grad():
        pred = torch.cat([net(torch.as_tensor(cur[i:i + 2048]), torch.as_tensor(tgt[i:i + 2048]))
                          .argmax(1) for i in range(0, len(cur), 2048)]).numpy()
    return float(good[np.arange(len(good)), pred].mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--alt", type=float, default=300.0, help="flight altitude, m")
    ap.add_argument("--regions", type=int, default=8, help="training regions of scene A")
    ap.add_argument("--held-out", type=int, default=4, help="held-out regions of scene A")
    ap.add_argument("--b-regions", type=int, default=4, help="regions of scene B")
    ap.add_argument("--scene-size", type=float, default=1100.0)
    ap.add_argument("--iters", type=int, default=2000, help="Adam steps of 256 pairs")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--encoder", choices=("cnn", "corr"), default="cnn",
                    help="the trainable SmallCNN (default) or the frozen correlation encoder")
    ap.add_argument("--corr-radius", type=int, default=8, help="encoder corr: shifts compared")
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    cache = Path(args.cache)
    s = int(args.scene_size)
    scene_a = ensure_scene(cache / f"probe-A{s}", "A", "residential", 0, args.scene_size, 0.5)
    scene_b = ensure_scene(cache / f"probe-B{s}", "B", "campus", 1, args.scene_size, 0.5)
    cam = Camera(PX)
    kw: dict[str, Any] = dict(size_m=140.0, alt_m=args.alt, step_m=20.0, max_steps=50,
                              camera=cam)
    ts_a = sample_meta_tasks(scene_a, args.regions + args.held_out, seed=0, **kw)
    ts_b = sample_meta_tasks(scene_b, args.b_regions, seed=3, **kw)
    tab_a = view_table(scene_a, ts_a)
    train = pairs(tab_a[:args.regions])
    held = pairs(tab_a[args.regions:])
    test_b = pairs(view_table(scene_b, ts_b))
    good = train[2]
    chance = {"random": float(good.mean()),
              "blind": float(good.mean(0).max())}
    net = ViewHead(args.seed, args.encoder, args.corr_radius)
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    rows = []
    for it in range(1, args.iters + 1):
        idx = rng.integers(len(good), size=256)
        logits = net(torch.as_tensor(train[0][idx]), torch.as_tensor(train[1][idx]))
        mask = torch.as_tensor(good[idx])
        loss = -(torch.logsumexp(logits.masked_fill(~mask, -1e9), 1)
                 - torch.logsumexp(logits, 1)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % max(args.iters // 4, 1) == 0:
            sub = rng.choice(len(good), size=min(4000, len(good)), replace=False)
            row = {"iter": it, "loss": round(loss.item(), 4),
                   "train": round(accuracy(net, train[0][sub], train[1][sub], good[sub]), 3),
                   "A_held_out": round(accuracy(net, *held), 3),
                   "B": round(accuracy(net, *test_b), 3),
                   "s": round(time.perf_counter() - t0)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    last = rows[-1]
    print(f"\nencoder {args.encoder}, alt {args.alt:g} m, {args.regions} training regions "
          f"of A ({len(good)} pairs); "
          f"fraction of view pairs whose action shortens the path:")
    print(f"  training pairs {last['train']:.3f} | held-out A regions {last['A_held_out']:.3f} "
          f"| scene B {last['B']:.3f} | chance: random {chance['random']:.3f}, "
          f"best view-blind {chance['blind']:.3f}")


if __name__ == "__main__":
    main()
