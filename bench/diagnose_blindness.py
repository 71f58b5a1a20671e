"""Why a learner ignores the image: activations across start cells, Adam's scales, ablations.

Reproduces the figures of docs/learning.md section 4 on the quick experiment's scene-B
task (built once under bench/.cache, as bench_learning.py does):

    python bench/diagnose_blindness.py layers --init savn --input-norm none --actor 0.01
    python bench/diagnose_blindness.py layers                      # today's defaults
    python bench/diagnose_blindness.py ablate --episodes 600 --seeds 0,1

``layers`` trains A3C (one process) and prints, at init and after training, each layer's
relative spread across the start views (std over cells / mean |a|), mean |activation|
and the share of units never active, plus the median sqrt(v) of Adam per parameter.
``ablate`` trains the variants of the table in docs/learning.md and prints greedy and
sampled SR/SPL over all starts and the spread of the first-step action probabilities.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import torch
from torch.nn import functional as F

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_learning import quick_b_env  # noqa: E402

from geonav.policy.a3c import A3CTrainer  # noqa: E402
from geonav.policy.agent import obs_inputs  # noqa: E402
from geonav.policy.config import A3CConfig, LossConfig, NetConfig  # noqa: E402
from geonav.policy.envs import EnvFactory  # noqa: E402
from geonav.policy.evaluation import evaluate_both  # noqa: E402
from geonav.policy.model import ActorCritic  # noqa: E402

# name -> (NetConfig overrides, A3CConfig overrides)
VARIANTS: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "savn-init (geonav 0.1)": ({"init": "savn", "input_norm": "none"}, {}),
    "savn-init, adam eps 1e-8": ({"init": "savn", "input_norm": "none"}, {"adam_eps": 1e-8}),
    "savn-init, tau 0.95": ({"init": "savn", "input_norm": "none"}, {"tau": 0.95}),
    "centre + orthogonal, actor 0.01": ({"actor_init_std": 0.01}, {}),
    "actor 1 only": ({"init": "savn", "input_norm": "none", "actor_init_std": 1.0}, {}),
    "centre + actor 1": ({"init": "savn", "actor_init_std": 1.0}, {}),
    "orthogonal + actor 1": ({"input_norm": "none"}, {}),
    "centre + orthogonal, actor 0.1": ({"actor_init_std": 0.1}, {}),
    "centre + orthogonal + actor 1 (default)": ({}, {}),
}


def _views(env: Any) -> tuple[torch.Tensor, torch.Tensor]:
    cells = env.unwrapped.start_cells(0)
    views = []
    for c in cells:
        obs, info = env.reset(options={"task": 0, "start_cell": c})
        v, t = obs_inputs(obs, info, None)
        views.append(v)
    return torch.stack(views), t


@torch.no_grad()
def layer_stats(model: ActorCritic, env: Any) -> dict[str, tuple[float, float, float]]:
    views, target = _views(env)
    f = model.features(views)
    ft = model.features(target[None])
    oe = F.relu(model.obs_embed(f))
    te = F.relu(model.target_embed(ft)).expand_as(oe)
    ae = F.relu(model.action_embed(torch.zeros(len(views), model.cfg.n_actions)))
    x = F.relu(model.fc(torch.cat([oe, te, ae], -1)))
    h, _ = model.lstm(x)
    out = {}
    for name, a in (("CNN features", f), ("view embedding", oe), ("FC", x), ("LSTM h", h),
                    ("logits", model.actor(h))):
        spread = float(a.std(0).mean() / (a.abs().mean() + 1e-12))
        dead = float(((a.abs() > 1e-9).float().mean(0) == 0).float().mean())
        out[name] = (spread, float(a.abs().mean()), dead)
    return out


def train(net_kw: dict[str, Any], cfg_kw: dict[str, Any], episodes: int, seed: int,
          factory: EnvFactory, n_px: int) -> tuple[A3CTrainer, int]:
    cfg_kw = dict(cfg_kw)
    loss = LossConfig(tau=cfg_kw.pop("tau", 1.0))
    net = NetConfig(encoder="cnn", obs_size_px=n_px, **net_kw)
    cfg = A3CConfig(episodes=episodes, workers=0, lr=5e-4, seed=seed, checkpoint_every=0,
                    eval_every=0, loss=loss, **cfg_kw)
    t = A3CTrainer(factory, net, cfg, keep_records=False, tensorboard=False)
    res = t.train()
    return t, res.env_steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mode", choices=["layers", "ablate"])
    ap.add_argument("--init", default="orthogonal")
    ap.add_argument("--input-norm", default="center")
    ap.add_argument("--actor", type=float, default=None, help="actor_init_std")
    ap.add_argument("--episodes", type=int, default=300)
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--variants", default=None, help="comma list of variant numbers (1-based)")
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    factory, env, n_px = quick_b_env(Path(args.cache))
    seeds = [int(s) for s in args.seeds.split(",")]
    if args.mode == "layers":
        net_kw = {"init": args.init, "input_norm": args.input_norm,
                  "actor_init_std": args.actor}
        torch.manual_seed(seeds[0])
        before = layer_stats(ActorCritic(NetConfig(obs_size_px=n_px, **net_kw)), env)
        t, _ = train(net_kw, {}, args.episodes, seeds[0], factory, n_px)
        after = layer_stats(t.model, env)
        print(f"{net_kw}, {args.episodes} episodes, seed {seeds[0]}")
        print("| layer | spread init -> trained | mean abs | never active |")
        print("|---|---|---|---|")
        for k in before:
            b, a = before[k], after[k]
            print(f"| {k} | {b[0]:.3f} -> {a[0]:.4f} | {b[1]:.3g} -> {a[1]:.3g} | "
                  f"{b[2]:.0%} -> {a[2]:.0%} |")
        eps = t.optimizer.param_groups[0]["eps"]
        print(f"\nAdam median sqrt(v) per parameter (eps {eps:g}):")
        for name, p in t.model.named_parameters():
            v = t.optimizer.state[p]["exp_avg_sq"].sqrt()
            print(f"  {name:22s} {float(v.median()):.2e}")
        return
    chosen = list(VARIANTS.items())
    if args.variants:
        chosen = [chosen[int(i) - 1] for i in args.variants.split(",")]
    print("| variant | seed | env steps | greedy SR | greedy SPL | sampled SR | sampled SPL |"
          " first-step prob std over cells | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, (net_kw, cfg_kw) in chosen:
        for seed in seeds:
            t0 = time.perf_counter()
            t, steps = train(net_kw, cfg_kw, args.episodes, seed, factory, n_px)
            res = evaluate_both(t.model, env, frozen=None, max_starts=None, seed=seed)
            views, target = _views(env)
            with torch.no_grad():
                m = t.model
                lg, _, _ = m(views[None], target[None].expand(len(views), *target.shape),
                             m.initial_state(len(views)))
            spread = float(torch.softmax(lg[0], -1).std(0).mean())
            r = res["row"]
            print(f"| {name} | {seed} | {steps} | {r['greedy_sr']:.2f} | {r['greedy_spl']:.2f} | "
                  f"{r['sampled_sr']:.2f} | {r['sampled_spl']:.2f} | {spread:.4f} | "
                  f"{time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
