"""Meta-training (Eq. 1, ALGORITHMS.md (d)) on the batched engine, SAVN base, E = 1.

A meta-iteration takes the next B meta-tasks in cyclic order and runs one SAVN episode on
each, all B at once: slot j of the round is pinned to task j of the batch and starts from
psi (:class:`~geonav.policy.batched.savn.BatchedSAVNTrainer`'s episode-synchronous
round). Task i's gradient g_i is its episode's exact meta-gradient w.r.t. its initial
parameters (= psi, and Lambda); then psi <- psi - eta sum_i g_i (SGD, or Adam as
``meta_optimizer``; ``meta_max_grad_norm`` clips the sum). With E = 1 the in-task Adam
of the reference (:class:`~geonav.policy.meta.MetaTrainer`) never changes a task
gradient (its step follows the only episode and is discarded), so this is the
reference's meta update exactly, for B tasks in one batch.

ISAR and A3C bases (their in-task Adam steps make every task's parameters differ within
its episode) and E > 1 run on the async engine.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch
from torch import nn

from geonav.errors import ConfigError
from geonav.policy.batched.savn import BatchedSAVNTrainer
from geonav.policy.config import to_dict
from geonav.policy.meta_config import MetaConfig, SAVNConfig
from geonav.vecenv import LatticeVecEnv


class BatchedMetaSAVN(BatchedSAVNTrainer):
    """Meta-training with the SAVN base on the batched engine (see the module docstring).

    Args as :class:`~geonav.policy.meta.MetaTrainer` with ``algo = 'savn'``; the batch is
    the meta-batch B (``meta_cfg.batch``).
    """

    config_key = "base"

    def __init__(self, env_factory: Any, net_cfg: Any, base_cfg: SAVNConfig,
                 meta_cfg: MetaConfig | None = None, **kwargs: Any) -> None:
        self.meta_cfg = m = meta_cfg if meta_cfg is not None else MetaConfig()
        if m.episodes_per_task != 1:
            raise ConfigError("batched meta-training runs E = 1 episode per task visit; "
                              "use engine = 'async' for more")
        self.algorithm = "meta-savn"
        base_cfg = replace(base_cfg, episodes=m.episodes, workers=m.workers, seed=m.seed,
                           checkpoint_every=m.checkpoint_every, torch_threads=m.torch_threads,
                           max_grad_norm=0.0)
        kwargs.pop("batch", None)
        super().__init__(env_factory, net_cfg, base_cfg, batch=m.batch, **kwargs)
        self.n_tasks = len(self.env.unwrapped.tasks)
        self.meta_updates = int(self.ckpt.meta.get("meta_updates", 0)
                                if self.ckpt is not None else 0)

    def build_optimizer(self, params: list[torch.Tensor]) -> torch.optim.Optimizer:
        m = self.meta_cfg
        if m.meta_optimizer == "adam":
            return torch.optim.Adam(params, lr=m.meta_lr)
        return torch.optim.SGD(params, lr=m.meta_lr)

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d.update({"meta": to_dict(self.meta_cfg), "base_algorithm": "savn",
                  "task_gradient": "exact meta-gradient w.r.t. the initial parameters"})
        return d

    def checkpoint_meta(self, episodes: int) -> dict[str, Any]:
        meta = super().checkpoint_meta(episodes)
        meta["config"]["meta"] = to_dict(self.meta_cfg)
        meta["config"]["base_algorithm"] = "savn"
        meta["meta_updates"] = self.meta_updates
        return meta

    def batch_tasks(self, visits: int) -> np.ndarray:
        """Slot j <- task (visits + j) mod M, visits = episodes so far (a resume goes on)."""
        return ((visits + np.arange(self.batch)) % self.n_tasks).astype(np.int64)

    def make_venv(self) -> LatticeVecEnv:
        self._visits = self.episodes_done
        return LatticeVecEnv(self.env, self.batch, slot_tasks=self.batch_tasks(self._visits))

    def next_round(self) -> None:
        self._visits += self.batch
        self.venv.slot_tasks = self.batch_tasks(self._visits)
        self.venv.reset()

    def step_optimizer(self, loss: torch.Tensor) -> None:
        """psi <- psi - eta * sum_i g_i: the round's loss is the mean over the B slots,
        so its gradient times B is the sum of the task gradients."""
        self.optimizer.zero_grad(set_to_none=True)
        (loss * self.batch).backward()
        m = self.meta_cfg
        for p in self.params_list:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        if self.on_gradients is not None:
            self.on_gradients([p.grad for p in self.params_list])
        if m.meta_max_grad_norm > 0:
            nn.utils.clip_grad_norm_(self.params_list, m.meta_max_grad_norm)
        self.optimizer.step()
        self.meta_updates += 1

    def update(self) -> tuple[list[dict[str, Any]], dict[str, float]]:
        finals, stats = super().update()
        for f in finals:
            f["meta_update"] = self.meta_updates
        return finals, stats

    def record(self, f: dict[str, Any], stats: dict[str, float]) -> dict[str, Any]:
        rec = super().record(f, stats)
        rec["meta_update"] = f["meta_update"]
        return rec


__all__ = ["BatchedMetaSAVN"]
