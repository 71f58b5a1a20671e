"""SAVN (ALGORITHMS.md (b)) on the batched engine, episode-synchronous, exact per episode.

The shared parameters are the policy P (phi) and the learned loss Lambda
(:class:`~geonav.policy.savn.InteractionLoss`, the async trainer's aux module, so
checkpoints hold it under ``extra['interaction_loss']`` as there). Every update is a
**round**: all B slots start an episode together with theta_s = phi and step in
lock-step, with the graph kept and h never detached:

* every k steps, each slot still in its episode with fewer than G inner steps takes
  theta_s <- theta_s - alpha grad_theta ||TCN_Lambda(X_s)||_2 (X_s: the segment's k rows
  [h_t, pi_t]; the TCN applied per slot with ``torch.func.vmap``; create_graph =
  ``second_order``); theta_s is phi plus exact per-slot rank-one factors
  (:mod:`geonav.policy.batched.core`);
* a slot whose episode ends waits (its later steps are masked out) until every slot
  has finished;
* the meta-loss is L_AC over each whole episode (B = 0 at its end), averaged over the
  slots; its gradient w.r.t. phi and Lambda (Lambda through the second-order path only)
  takes one Adam step.

* with ``bootstrap_on_truncation`` an episode cut by the step cap bootstraps its
  meta-loss with V(s_T) under its last theta_s, detached, as the reference does.

So each episode is exactly the reference worker's episode (``tests/test_batched_savn.py``
compares B = 1), and a round's update is the mean of B episodes' meta-gradients. Waiting
slots cost forward passes: a round lasts as long as its longest episode. With the
trainable CNN theta_s adapts the convolutions too (dense per-slot weight changes,
:class:`~geonav.policy.batched.core.SlotDeltas`): each slot's current view is encoded once
per step and its target once per segment under its own weights, with the graph.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from geonav.policy.batched.core import Adapted, Recorder, factored_step, sample_actions
from geonav.policy.batched.isar import gram_matrix, values_dtype
from geonav.policy.batched.teacher import BatchedTeacher
from geonav.policy.batched.trainer import BatchedTrainer, loss_stats
from geonav.policy.isar import gradient_path, teacher_record
from geonav.policy.losses import LossTerms, gae_returns, policy_value_terms
from geonav.policy.meta_config import SAVNConfig
from geonav.policy.savn import InteractionLoss


class BatchedSAVNTrainer(BatchedTrainer):
    """SAVN on the batched engine (see the module docstring); ``cfg`` is a :class:`SAVNConfig`."""

    algorithm = "savn"
    config_key = "savn"
    cfg: SAVNConfig

    def __init__(self, env_factory: Any, net_cfg: Any = None, cfg: SAVNConfig | None = None,
                 *, teacher: Any = None, prev_view: Any = None, **kwargs: Any) -> None:
        self.teacher_spec = teacher
        self.prev_view_spec = prev_view
        super().__init__(env_factory, net_cfg, cfg if cfg is not None else SAVNConfig(),
                         **kwargs)

    def _setup(self) -> None:
        super()._setup()
        self.gram = gram_matrix(self.table)
        self.teacher = BatchedTeacher(self.teacher_spec, self.batch, self.device) \
            if self.teacher_spec is not None else None

    def build_aux(self) -> dict[str, nn.Module]:
        return {"interaction_loss": InteractionLoss(self.cfg.k_steps, self.cfg.tcn_channels)}

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d["gradient_path"] = {**gradient_path(self.cfg), "path": "batched factored, "
                              "episode-synchronous rounds"}
        d["teacher"] = teacher_record(self.teacher_spec, self.prev_view_spec)
        return d

    def record(self, f: dict[str, Any], stats: dict[str, float]) -> dict[str, Any]:
        rec = super().record(f, stats)
        rec.update({"inner_updates": f["inner_updates"], "adaptive_updates": 1,
                    "kl_weight": f.get("kl_weight", 0.0)})
        return rec

    def next_round(self) -> None:
        """Every slot starts a new episode (meta-training pins their tasks first)."""
        self.venv.reset()

    def round_slots(self) -> np.ndarray:
        """(B,) bool: the slots that play an episode in this round (every one here;
        meta-training leaves out the slots without a task visit at the end of its budget).
        The others step masked, as a slot whose episode has ended."""
        return np.ones(self.batch, bool)

    def interaction_loss(self, rows: torch.Tensor) -> torch.Tensor:
        """(B, k, H + A) -> (B,) learned losses, the aux module applied per slot."""
        tcn = self.aux_module()
        lam, dim = self.loss_params()
        return torch.func.vmap(lambda p, r: torch.func.functional_call(tcn, p, (r,)),
                               in_dims=(dim, 0))(lam, rows)

    def aux_module(self) -> nn.Module:
        return self.aux["interaction_loss"]

    def loss_params(self) -> tuple[dict[str, torch.Tensor], int | None]:
        """Lambda, shared by the slots (vmap in_dims None); packed runs: per slot, dim 0."""
        return dict(self.aux_module().named_parameters()), None

    def update(self) -> tuple[list[dict[str, Any]], dict[str, float]]:
        cfg, e, dev, b = self.cfg, self.net_cfg.embed_dim, self.device, self.batch
        dtype = values_dtype(self)
        venv = self.venv  # every slot is at the start of an episode (reset after a round)
        params = self.params()
        adapted: Adapted = {}
        z = torch.zeros(b, self.net_cfg.lstm_size, dtype=dtype, device=dev)
        state = (z, z.clone(), torch.zeros(b, self.net_cfg.n_actions, dtype=dtype, device=dev))
        alive = self.round_slots()
        inner = np.zeros(b, np.int64)
        logits, values, actions, rewards, ends, masks = [], [], [], [], [], []
        finals: list[dict[str, Any]] = []
        lc = cfg.loss
        end_values = [] if lc.bootstrap_on_truncation else None
        t = 0
        rec = Recorder(gram=self.gram)
        tgt_f: torch.Tensor | None = None  # the targets' features under the current theta
        hs: list[torch.Tensor] = []
        kls: list[torch.Tensor] = []
        # the curriculum teacher's lambda of each slot's episode (numbered in slot order)
        lam = torch.tensor([self.teacher.weight(self.episodes_done + 1 + s) for s in range(b)],
                           dtype=dtype, device=dev) if self.teacher is not None else None
        while alive.any():
            vi, ti = self.slot_indices()
            tlogp = self.teacher.step(vi, ti, torch.full((b,), t == 0, device=dev),
                                      venv.feasible_moves()
                                      if self.teacher.spec.mask != "none" else None) \
                if self.teacher is not None else None
            if tgt_f is None:
                tgt_f = self.slot_views(params, adapted, ti, rec)
            logit, value, state = factored_step(params, e, self.slot_views(params, adapted, vi,
                                                                           rec),
                                                tgt_f, state, adapted, rec, None, vi, ti,
                                                self.slot_prev(params, adapted, vi, rec))
            hs.append(state[0])
            if tlogp is not None and lam is not None:  # lambda KL(pi_T || pi_theta), (B,)
                kls.append(self.teacher.terms(tlogp[None].to(dtype), logit[None])[0] * lam)
                self.teacher.observe(tlogp[None], logit.detach()[None], self.episodes_done,
                                     torch.from_numpy(alive)[None].to(dev))
            a = sample_actions(logit, self.rng, alive).to(dev)  # draws for live slots only
            res = venv.step(a.cpu().numpy(), autoreset=False)
            if end_values is not None:  # V(s_T) under theta_s at a truncation, detached
                end_values.append(np.zeros(b))
                if (res.truncated & alive).any():
                    with torch.no_grad():
                        fv = torch.from_numpy(res.final_view).to(dev)
                        _, v_end, _ = factored_step(params, e, self.slot_views(params, adapted,
                                                                               fv),
                                                    tgt_f, state, adapted, None, None, fv, ti,
                                                    self.slot_prev(params, adapted, fv))
                    end_values[-1] = np.where(res.truncated & alive, v_end.cpu().numpy(), 0.0)
            logits.append(logit)
            values.append(value)
            actions.append(a)
            masks.append(torch.from_numpy(alive.copy()).to(dev, dtype))
            rewards.append(np.where(alive, res.rewards, 0.0))
            ends.append(res.done & alive)
            for f in res.final:
                if alive[f["slot"]]:
                    f["inner_updates"] = int(inner[f["slot"]])
                    f["kl_weight"] = float(lam[f["slot"]]) if lam is not None else 0.0
                    finals.append(f)
            alive &= ~res.done
            t += 1
            if t % cfg.k_steps == 0:
                can = alive & ((inner < cfg.inner_steps) | (cfg.inner_steps < 0))
                if can.any():
                    seg_h = torch.stack(hs[-cfg.k_steps:], 1)                    # (B, k, H)
                    seg_p = F.softmax(torch.stack(logits[-cfg.k_steps:], 1), -1)
                    l_int = self.interaction_loss(torch.cat([seg_h, seg_p], -1))
                    if kls:
                        l_int = l_int + torch.stack(kls[-cfg.k_steps:]).sum(0)
                    w = torch.from_numpy(can).to(dev, dtype)
                    adapted = rec.inner_factors((l_int * w).sum(), adapted, cfg.inner_lr,
                                                create_graph=cfg.second_order, weights=w)
                    inner += can
                rec = Recorder(gram=self.gram)
                tgt_f = None
        mask = torch.stack(masks)
        ends_np = np.stack(ends)
        lg, vs, acts = torch.stack(logits), torch.stack(values), torch.stack(actions)
        ret, adv = gae_returns(np.stack(rewards), vs.detach().to("cpu", torch.float64).numpy(),
                               np.zeros(b), ends_np, lc.gamma, lc.tau,
                               None if end_values is None else np.stack(end_values))
        ret_t, adv_t = torch.from_numpy(ret).to(dev, dtype), torch.from_numpy(adv).to(dev, dtype)
        weights = [mask if m is None else mask * m for m in self.run_masks(mask)]
        runs = [policy_value_terms(lg, vs, acts, ret_t, adv_t, lc, weights=w)
                for w in weights]  # one run; one per run when packed
        total = torch.stack([r.total for r in runs]).sum()
        if kls:
            total = total + (torch.stack(kls) * mask).sum()
        bf = float(self.run_batch)
        self.step_optimizer(total / bf)
        self.fresh = torch.ones(b, dtype=torch.bool, device=dev)
        for f in finals:
            f["t0"] = float(self.t_episode[f["slot"]])
        self.next_round()
        self.t_episode[:] = time.perf_counter()
        stats = self.update_stats(runs, weights, kls, mask)
        return finals, stats[0] if len(stats) == 1 else stats

    def update_stats(self, runs: list[LossTerms], weights: list[torch.Tensor],
                     kls: list[torch.Tensor], mask: torch.Tensor) -> list[dict[str, float]]:
        """The metrics of an update, one row per run, with the teacher's columns."""
        bf = float(self.run_batch)
        stats = [loss_stats(LossTerms(r.total / bf, r.policy / bf, r.value / bf,
                                      r.entropy / bf), int(w.sum()) // self.run_batch)
                 for r, w in zip(runs, weights, strict=True)]
        if self.teacher is not None:  # unpacked: one run
            stats[0].update({"teacher_loss": float((torch.stack(kls) * mask).sum()) / bf,
                             **self.teacher.report()})
        return stats


__all__ = ["BatchedSAVNTrainer"]
