"""Packed runs: several independent batched-A3C runs in one process batch.

Each run has its own parameters, Adam state, seeds, environment slots (``batch`` per
run, default 16) and gradient clipping, exactly as if it ran alone
(:class:`~geonav.policy.batched.trainer.BatchedA3CTrainer`); the runs' parameters are
stacked along a leading run dimension and every network call is one
``torch.func.vmap`` over the runs of the same batched forward
(:mod:`geonav.policy.batched.core`), so R runs of B slots cost about one run of R x B
slots. One Adam over the stacked tensors is R independent Adams (Adam is elementwise
and the runs step together); the norm clip is taken per run.

Why a per-run batch rather than one run of R x B slots: a run's updates per episode
stay those of a B-worker A3C (B = 16 is the order of the paper's and SAVN's worker
counts), so episodes-to-convergence stay comparable with the paper's; a run of 256
slots takes one update per 256 x t_max steps, 16 times fewer updates per episode, and
needs many more episodes to converge even though each second holds more of them.

Each run writes its own folder ``run_<i>/`` (metrics.csv with the trainer's columns,
config.json, checkpoints/final.pt in the checkpoint format of every trainer), so
``geonav eval`` and ``fly`` read it. Resume is not implemented for packed runs.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from geonav.errors import ConfigError
from geonav.policy.batched.core import Params, core_step, sample_actions
from geonav.policy.batched.core import sequence_forward as _sequence_forward
from geonav.policy.batched.trainer import DEFAULT_BATCH, resolve_device
from geonav.policy.callbacks import CSVMetrics
from geonav.policy.checkpoint import make_meta, save_checkpoint
from geonav.policy.config import A3CConfig, NetConfig, to_dict
from geonav.policy.encoders import build_frozen_encoder
from geonav.policy.evaluation import spl
from geonav.policy.losses import gae_returns, policy_value_terms
from geonav.policy.model import ActorCritic
from geonav.vecenv import LatticeVecEnv


def _tables(params: Params, embed_dim: int, feats: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """(C, H) image parts of every view as current view and as target (no factors)."""
    w = params["fc.weight"]
    obs_e = torch.relu(torch.nn.functional.linear(feats, params["obs_embed.weight"],
                                                  params["obs_embed.bias"]))
    tgt_e = torch.relu(torch.nn.functional.linear(feats, params["target_embed.weight"],
                                                  params["target_embed.bias"]))
    return (torch.nn.functional.linear(obs_e, w[:, :embed_dim]),
            torch.nn.functional.linear(tgt_e, w[:, embed_dim:2 * embed_dim], params["fc.bias"]))


class PackedA3C:
    """R batched-A3C runs in one process batch (see the module docstring).

    Args:
        env_factory: the environment of every run (its tasks and rewards).
        net_cfg: the architecture of every run (a frozen encoder).
        cfg: A3C settings of every run; ``cfg.episodes`` is each run's budget.
        seeds: one seed per run (model init, environment and action draws, as a lone
            :class:`BatchedA3CTrainer` with ``cfg.seed = seed``).
        batch: slots per run.
        device: 'cpu' or 'cuda'.
        out_dir: folder of the run folders (None: in memory).
    """

    def __init__(self, env_factory: Any, net_cfg: NetConfig, cfg: A3CConfig,
                 seeds: Sequence[int], *, batch: int = DEFAULT_BATCH,
                 device: str | None = "cpu", out_dir: Any = None) -> None:
        if not seeds:
            raise ConfigError("packed runs need at least one seed")
        if net_cfg.encoder == "cnn" or net_cfg.prev_view_input:
            raise ConfigError("packed runs need a frozen encoder and no previous-view slot")
        self.cfg, self.net_cfg, self.seeds = cfg, net_cfg, [int(s) for s in seeds]
        self.batch, self.device = int(batch), resolve_device(device)
        self.env = env_factory()
        self.frozen = build_frozen_encoder(net_cfg)
        models = []
        for s in self.seeds:
            torch.manual_seed(s)
            models.append(ActorCritic(net_cfg))
        self.names = [n for n, _ in models[0].named_parameters()]
        self.params: Params = {
            n: torch.stack([dict(m.named_parameters())[n].detach() for m in models])
            .to(self.device).requires_grad_(True) for n in self.names}
        self.optimizer = torch.optim.Adam(list(self.params.values()), lr=cfg.lr,
                                          betas=cfg.adam_betas, eps=cfg.adam_eps,
                                          amsgrad=cfg.amsgrad, fused=cfg.fused or None)
        self.venvs = [LatticeVecEnv(self.env, self.batch) for _ in self.seeds]
        self.rngs = [np.random.default_rng(s) for s in self.seeds]
        for v, s in zip(self.venvs, self.seeds, strict=True):
            v.seed(s)
            v.reset()
        self.table = self.venvs[0].feature_table(self.frozen).to(self.device)
        r, b = len(self.seeds), self.batch
        z = torch.zeros(r, b, net_cfg.lstm_size, device=self.device)
        self.state = (z, z.clone(), torch.zeros(r, b, net_cfg.n_actions, device=self.device))
        self.fresh = torch.ones(r, b, dtype=torch.bool, device=self.device)
        self.episodes = [0] * r
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.records: list[list[dict[str, Any]]] = [[] for _ in self.seeds]
        self.env_steps = 0
        e = net_cfg.embed_dim
        self._tables = torch.func.vmap(lambda p: _tables(p, e, self.table))
        self._step = torch.func.vmap(lambda p, s, pre: core_step(p, e, s, pre=pre))
        self._seq = torch.func.vmap(
            lambda p, vi, ti, s, st: _sequence_forward(p, e, self.table, vi, ti, s, st))

    def _indices(self) -> tuple[torch.Tensor, torch.Tensor]:
        vi = torch.from_numpy(np.stack([v.view_index for v in self.venvs])).to(self.device)
        ti = torch.from_numpy(np.stack([v.target_index for v in self.venvs])).to(self.device)
        return vi, ti

    def update(self) -> list[list[dict[str, Any]]]:
        """One rollout of t_max steps in every run and one Adam step per run."""
        cfg, r, b, t_max = self.cfg, len(self.seeds), self.batch, self.cfg.t_max
        runs = torch.arange(r, device=self.device)[:, None]
        finals: list[list[dict[str, Any]]] = [[] for _ in range(r)]
        with torch.no_grad():
            obs_pre, tgt_pre = self._tables(self.params)                       # (R, C, H)
            keep = (~self.fresh).unsqueeze(-1)
            start_state = (self.state[0] * keep, self.state[1] * keep, self.state[2] * keep)
            state = start_state
            vis, tis, acts, starts = [], [], [], []
            rewards = np.zeros((r, t_max, b))
            ends = np.zeros((r, t_max, b), bool)
            for t in range(t_max):
                vi, ti = self._indices()
                starts.append(self.fresh)
                keep = (~self.fresh).unsqueeze(-1)
                state = (state[0] * keep, state[1] * keep, state[2] * keep)
                logits, _, state = self._step(self.params, state,
                                              obs_pre[runs, vi] + tgt_pre[runs, ti])
                a = torch.stack([sample_actions(logits[i], self.rngs[i]) for i in range(r)])
                done = np.zeros((r, b), bool)
                for i, v in enumerate(self.venvs):
                    res = v.step(a[i].numpy())
                    rewards[i, t], ends[i, t], done[i] = res.rewards, res.done, res.done
                    finals[i] += res.final
                self.fresh = torch.from_numpy(done).to(self.device)
                vis.append(vi)
                tis.append(ti)
                acts.append(a.to(self.device))
            vi, ti = self._indices()
            _, v_next, _ = self._step(self.params, state, obs_pre[runs, vi] + tgt_pre[runs, ti])
        self.state = state
        view_idx = torch.stack(vis, 1)                                             # (R, T, B)
        target_idx = torch.stack(tis, 1)
        logits, values, _ = self._seq(self.params, view_idx, target_idx, start_state,
                                      torch.stack(starts, 1))
        lc = cfg.loss
        vals = values.detach().to("cpu", torch.float64).numpy()
        boot = np.where(ends[:, -1], 0.0, v_next.to("cpu", torch.float64).numpy())
        ret = np.zeros_like(vals)
        adv = np.zeros_like(vals)
        for i in range(r):
            ret[i], adv[i] = gae_returns(rewards[i], vals[i], boot[i], ends[i], lc.gamma,
                                         lc.tau)
        dev, dt = self.device, values.dtype
        terms = policy_value_terms(logits, values, torch.stack(acts, 1),
                                   torch.from_numpy(ret).to(dev, dt),
                                   torch.from_numpy(adv).to(dev, dt), lc)
        self.optimizer.zero_grad(set_to_none=True)
        (terms.total / b).backward()
        if cfg.max_grad_norm:  # clip_grad_norm_ per run
            grads = [p.grad for p in self.params.values() if p.grad is not None]
            norms = torch.stack([g.flatten(1).pow(2).sum(1) for g in grads]).sum(0).sqrt()
            coef = (cfg.max_grad_norm / (norms + 1e-6)).clamp(max=1.0)
            for g in grads:
                g.mul_(coef.view(-1, *([1] * (g.dim() - 1))))
        self.optimizer.step()
        self.env_steps += r * b * t_max
        return finals

    def train(self) -> list[list[dict[str, Any]]]:
        """Until every run has ``cfg.episodes`` episodes; returns each run's records."""
        csvs = []
        if self.out_dir is not None:
            for i, s in enumerate(self.seeds):
                d = self.out_dir / f"run_{i}"
                (d / "checkpoints").mkdir(parents=True, exist_ok=True)
                (d / "config.json").write_text(json.dumps({
                    "algorithm": "a3c", "net": to_dict(self.net_cfg),
                    "a3c": {**to_dict(self.cfg), "seed": s},
                    "engine": {"name": "batched-packed", "runs": len(self.seeds),
                               "batch": self.batch, "device": str(self.device)}}, indent=1))
                csvs.append(CSVMetrics(d / "metrics.csv"))
        t0 = time.perf_counter()
        threads = torch.get_num_threads()
        torch.set_num_threads(self.cfg.torch_threads)
        try:
            while min(self.episodes) < self.cfg.episodes:
                for i, fins in enumerate(self.update()):
                    for f in fins[:self.cfg.episodes - self.episodes[i]]:
                        self.episodes[i] += 1
                        rec = {"episode": self.episodes[i], "worker": f["slot"],
                               "task": f["task"], "task_index": f["task_index"],
                               "return": f["return"], "length": f["length"],
                               "success": f["success"],
                               "spl": spl(f["success"], f["shortest_path"], f["length"]),
                               "collisions": f["collisions"],
                               "shortest_path": f["shortest_path"], "env_steps": f["length"],
                               "elapsed_s": round(time.perf_counter() - t0, 3)}
                        self.records[i].append(rec)
                        if csvs:
                            csvs[i].on_episode(rec)
        finally:
            torch.set_num_threads(threads)
            for c in csvs:
                c.close()
        if self.out_dir is not None:
            for i in range(len(self.seeds)):
                model = self.model(i)
                meta = make_meta(self.net_cfg, self.frozen, self.env, algorithm="a3c",
                                 episodes=self.episodes[i],
                                 config={"a3c": {**to_dict(self.cfg), "seed": self.seeds[i]}})
                save_checkpoint(self.out_dir / f"run_{i}" / "checkpoints" / "final.pt",
                                model.state_dict(), meta)
        return self.records

    def model(self, i: int) -> ActorCritic:
        """Run i's network as a plain ActorCritic (CPU)."""
        m = ActorCritic(self.net_cfg)
        m.load_state_dict({n: self.params[n][i].detach().cpu() for n in self.names})
        return m


__all__ = ["PackedA3C"]
