"""ISAR (ALGORITHMS.md (c)) on the batched engine, with exact factored per-episode theta.

phi is the model's parameters (Adam with lr beta = ``cfg.lr``); each slot's interaction
policy theta_s is phi plus its own rank-one factors
(:class:`~geonav.policy.batched.core.Factors`), exact, not approximated. All slots act in
lock-step with the graph kept (``factored_step``), on a global clock:

* a **segment** is N steps; at every segment end each slot's segment loss L_AC(theta_s; S)
  (masked GAE, bootstrap V(s_next) under theta_s, detached; 0 at an episode end) joins the
  window; at the first K - 1 segment ends of a window every live slot takes its inner
  step theta_s <- theta_s - alpha grad L_AC (``create_graph = second_order``), from the
  steps of its current episode only;
* a **window** is K segments; at its end the adaptive update takes the gradient of the
  window's losses summed over its segments and averaged over the slots w.r.t. phi (clip,
  one Adam step), resets every theta_s to the new phi and detaches h and the
  previous-action input;
* a slot whose episode ends mid-window starts a new episode at once with theta_s = phi
  (its factors cleared) and h = 0; the finished episode's losses stay in the window
  (the partial window is flushed at the window end: phi has not changed since they were
  taken, so this is the same gradient as a flush at done). With
  ``flush_partial_window = false`` an episode that ends before the window's last segment
  has its steps in the window dropped from the window's loss instead, as the reference
  worker empties its partial window at done without an adaptive update.

With B = 1 the first episode follows Algorithm 1 exactly; later episodes (and every
episode at B > 1) begin wherever the global clock stands, so their first segment and
window may be shorter than N and K. This is the synchronous form of ISAR, as batched A3C
is of A3C; the asynchronous per-episode schedule stays in :mod:`geonav.policy.isar`
(``engine = "async"``). With the trainable CNN, theta_s adapts the convolutions too
(dense per-slot weight changes, :class:`~geonav.policy.batched.core.SlotDeltas`): each
slot's current view is encoded once per step and its target once per segment (and at a
new episode) under its own weights, with the graph, in one grouped call for the B slots.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from geonav.policy.batched.core import Adapted, Recorder, factored_step, sample_actions
from geonav.policy.batched.teacher import BatchedTeacher
from geonav.policy.batched.trainer import BatchedTrainer, loss_stats
from geonav.policy.isar import gradient_path, teacher_record
from geonav.policy.losses import LossTerms, gae_returns, policy_value_terms
from geonav.policy.meta_config import ISARConfig
from geonav.policy.model import detach_state


def clear_slots(adapted: Adapted, keep: torch.Tensor) -> Adapted:
    """theta_s <- phi for the slots where ``keep`` (B,) is 0 (their factors and CNN weight
    changes zeroed)."""
    return {key: f.cleared(keep) for key, f in adapted.items()}


class BatchedISARTrainer(BatchedTrainer):
    """ISAR on the batched engine (see the module docstring); ``cfg`` is an :class:`ISARConfig`."""

    algorithm = "isar"
    config_key = "isar"
    cfg: ISARConfig

    def __init__(self, env_factory: Any, net_cfg: Any = None, cfg: ISARConfig | None = None,
                 *, teacher: Any = None, prev_view: Any = None, **kwargs: Any) -> None:
        self.teacher_spec = teacher
        self.prev_view_spec = prev_view
        cfg = cfg if cfg is not None else ISARConfig()
        super().__init__(env_factory, net_cfg, cfg, **kwargs)

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d["gradient_path"] = {**gradient_path(self.cfg), "path": "batched factored",
                              "inner_updates": "per-slot rank-one factors of every linear "
                              "layer, autograd.grad w.r.t. the layer outputs (create_graph="
                              f"{self.cfg.second_order})"}
        d["teacher"] = teacher_record(self.teacher_spec, self.prev_view_spec)
        return d

    def _setup(self) -> None:
        super()._setup()
        self.gram = gram_matrix(self.table)
        self.teacher = BatchedTeacher(self.teacher_spec, self.batch, self.device) \
            if self.teacher_spec is not None else None
        self.inner = np.zeros(self.batch, np.int64)
        self.adapt = np.zeros(self.batch, np.int64)

    def record(self, f: dict[str, Any], stats: dict[str, float]) -> dict[str, Any]:
        rec = super().record(f, stats)
        rec.update({"inner_updates": f["inner_updates"], "adaptive_updates":
                    f["adaptive_updates"], "kl_weight": self.teacher.weight(f["started_as"])
                    if self.teacher is not None else 0.0})
        return rec

    def segment(self, params: Any, adapted: Adapted, state: Any, keep: bool = False
                ) -> tuple[torch.Tensor, list[LossTerms], LossTerms, Recorder, Adapted, Any,
                           list[dict[str, Any]], SegmentData]:
        """N lock-step steps with the graph: (all-steps loss, its terms per run,
        current-episode loss, recorder, adapted weights (finished slots reset to phi),
        state, finished episodes, the segment's data; with ``keep`` it holds what a replay
        of the segment needs)."""
        cfg, e, dev = self.cfg, self.net_cfg.embed_dim, self.device
        n, b = cfg.n_steps, self.batch
        ppo = cfg.base_loss == "ppo"
        rec = Recorder(gram=self.gram)
        logits, values, actions, tlogp, lams = [], [], [], [], []
        views: list[torch.Tensor] = []
        targets: list[torch.Tensor] = []
        starts: list[torch.Tensor] = []
        done_at: list[torch.Tensor | None] = []
        rewards = np.zeros((n, b))
        ends = np.zeros((n, b), bool)
        episodes = np.zeros((n, b), np.int64)
        end_values = np.zeros((n, b)) if cfg.loss.bootstrap_on_truncation else None
        current = torch.ones(n, b, dtype=values_dtype(self), device=dev)
        finals: list[dict[str, Any]] = []
        tgt_f: torch.Tensor | None = None
        for t in range(n):
            vi, ti = self.slot_indices()
            if self.teacher is not None:
                tlogp.append(self.teacher.step(vi, ti, self.fresh, self.venv.feasible_moves()
                                               if self.teacher.spec.mask != "none" else None))
                lams.append([self.teacher.weight(int(k)) for k in self.slot_episode])
            if keep:
                views.append(vi)
                targets.append(ti)
                starts.append(self.fresh)
            tgt_f = self.slot_targets(params, adapted, ti, rec, tgt_f)
            logit, value, state = factored_step(params, e, self.slot_views(params, adapted, vi,
                                                                           rec),
                                                tgt_f, state, adapted, rec, self.fresh, vi, ti,
                                                self.slot_prev(params, adapted, vi, rec))
            a = sample_actions(logit, self.rng).to(dev)
            episodes[t] = self.slot_episode
            res = self.env_step(a)
            done_at.append(None)
            if end_values is not None and res.truncated.any():
                with torch.no_grad():
                    fv = torch.from_numpy(res.final_view).to(dev)
                    _, v_end, _ = factored_step(params, e, self.slot_views(params, adapted, fv),
                                                tgt_f, state, adapted, None, None, fv, ti,
                                                self.slot_prev(params, adapted, fv))
                end_values[t] = np.where(res.truncated, v_end.cpu().numpy(), 0.0)
            logits.append(logit)
            values.append(value)
            actions.append(a)
            rewards[t] = res.rewards
            ends[t] = res.done
            if res.done.any():
                done = torch.from_numpy(res.done).to(dev)
                done_at[-1] = done
                current[:t + 1, done] = 0.0  # later inner steps see the new episode only
                adapted = clear_slots(adapted, (~done).to(current.dtype))
                for f in res.final:
                    s = f["slot"]
                    f["inner_updates"], f["adaptive_updates"] = int(self.inner[s]), \
                        int(self.adapt[s]) + 1  # its losses go into this window's update
                    self.inner[s] = self.adapt[s] = 0
                finals += res.final
        with torch.no_grad():  # V(s_next) under theta_s, without advancing the state
            vi, ti = self.slot_indices()
            _, v_next, _ = factored_step(params, e, self.slot_views(params, adapted, vi),
                                         self.slot_targets(params, adapted, ti, None, tgt_f),
                                         state, adapted, None, self.fresh, vi, ti,
                                         self.slot_prev(params, adapted, vi))
        lg = torch.stack(logits)
        if tlogp:
            assert self.teacher is not None
            self.teacher.observe(torch.stack(tlogp), lg.detach(), self.episodes_done)
        masks = self.run_masks(current)  # one run; one per run when packed
        vs, acts = torch.stack(values), torch.stack(actions)
        ret_t, adv_t = segment_advantages(vs, rewards, ends, v_next, cfg.loss, end_values)
        data = SegmentData(
            views, targets, starts, done_at, acts, ret_t, adv_t, [*masks, current],
            # the acting policy's log pi_old(a_t): theta_s of this segment, as acted
            torch.log_softmax(lg.detach(), -1).gather(-1, acts.unsqueeze(-1)).squeeze(-1)
            if ppo else None,
            torch.stack(tlogp).to(lg.dtype) if tlogp else None,
            torch.tensor(lams, dtype=lg.dtype, device=dev) if tlogp else None,
            episodes=episodes, logits=lg, values=vs)
        total, runs, mine = self.segment_loss(lg, vs, data)
        return total, runs, mine, rec, adapted, state, finals, data

    def segment_loss(self, logits: torch.Tensor, values: torch.Tensor, d: SegmentData
                     ) -> tuple[torch.Tensor, list[LossTerms], LossTerms]:
        """(all-steps loss, its terms per run, current-episode loss) of a segment's
        logits (N, B, A) and values (N, B): L_AC, or with ``base_loss = 'ppo'`` the clipped
        surrogate against the acting log-probs, plus the curriculum's KL prior."""
        cfg = self.cfg
        *runs, mine = segment_losses(logits, values, d.actions, d.returns, d.advantages,
                                     cfg.loss, d.weights, d.old_logprobs, cfg.clip_coef)
        total = torch.stack([r.total for r in runs]).sum()
        if d.teacher_logprobs is not None:  # + lambda KL(pi_T || pi_theta) in every L_int,
            assert d.kl_weights is not None and self.teacher is not None  # lambda (N, B)
            kl = self.teacher.terms(d.teacher_logprobs, logits) * d.kl_weights
            total = total + kl.sum()
            current = d.weights[-1]
            assert current is not None
            mine = replace(mine, total=mine.total + (kl * current).sum())
        return total, runs, mine

    def replay_segment(self, params: Any, adapted: Adapted, state: Any, d: SegmentData
                       ) -> tuple[torch.Tensor, list[LossTerms], LossTerms, Recorder,
                                  Adapted, Any]:
        """A kept segment recomputed under ``params`` and ``adapted`` (a PPO pass after
        the first): the same views, episode starts and ends and actions, no env step."""
        e = self.net_cfg.embed_dim
        rec = Recorder(gram=self.gram)
        logits, values = [], []
        tgt_f: torch.Tensor | None = None
        for vi, ti, start, done in zip(d.views, d.targets, d.starts, d.done_at, strict=True):
            # as the acting pass: the trainable CNN encodes each slot's views under its own
            # adapted weights, its target once per segment and at a new episode
            tgt_f = self.slot_targets(params, adapted, ti, rec, tgt_f, start)
            logit, value, state = factored_step(params, e, self.slot_views(params, adapted, vi,
                                                                           rec),
                                                tgt_f, state, adapted, rec, start, vi, ti,
                                                self.slot_prev(params, adapted, vi, rec))
            logits.append(logit)
            values.append(value)
            if done is not None:
                adapted = clear_slots(adapted, (~done).to(values_dtype(self)))
        total, runs, mine = self.segment_loss(torch.stack(logits), torch.stack(values), d)
        return total, runs, mine, rec, adapted, state

    def update(self) -> tuple[list[dict[str, Any]], Any]:
        """One window of K segments and its adaptive update (``ppo_epochs`` of them with
        ``base_loss = 'ppo'``: the later passes replay the window under the new phi)."""
        cfg = self.cfg
        params = self.params()
        adapted: Adapted = {}
        state0 = state = self.state
        window: list[torch.Tensor] = []
        finals: list[dict[str, Any]] = []
        kept: list[SegmentData] = []
        replays = cfg.ppo_epochs - 1 if cfg.base_loss == "ppo" else 0
        sums = np.zeros((len(self.run_slices()), 3))  # policy, value, entropy per run
        dropped: list[tuple[int, int]] = []
        for k in range(cfg.k_segments):
            total, runs, mine, rec, adapted, state, fin, data = self.segment(
                params, adapted, state, keep=replays > 0)
            if not cfg.flush_partial_window and k < cfg.k_segments - 1:
                for f in fin:  # ended in a partial window: its losses leave the window
                    f["adaptive_updates"] -= 1
                    dropped.append((f["slot"], f["started_as"]))
            finals += fin
            window.append(total)
            sums += [[float(r.policy.detach()), float(r.value.detach()),
                      float(r.entropy.detach())] for r in runs]
            if k < cfg.k_segments - 1:
                live = (~self.fresh).to(values_dtype(self))
                adapted = rec.inner_factors(mine.total, adapted, cfg.alpha,
                                            create_graph=cfg.second_order, weights=live)
                self.inner += (~self.fresh).cpu().numpy()
                data.live = live
            kept.append(data)
        if dropped:
            window = self.drop_episodes(kept, window, dropped)
        self.step_optimizer(torch.stack(window).sum() / self.run_batch)
        for _ in range(replays):
            sums = self.replay_window(state0, kept)
        # a slot whose episode ended at the window's last step has no step of its new one
        # in this window: the update is not the new episode's
        self.adapt += (~self.fresh).cpu().numpy()
        self.state = detach_state(state)
        b = float(self.run_batch)
        stats = [loss_stats(LossTerms(torch.tensor(0.0), torch.tensor(pl / b),
                                      torch.tensor(vl / b), torch.tensor(ent / b)),
                            cfg.n_steps * cfg.k_segments) for pl, vl, ent in sums]
        if self.teacher is not None:  # unpacked: one run
            stats[0].update(self.teacher_stats(kept))
        return finals, stats[0] if len(stats) == 1 else stats

    def teacher_stats(self, kept: list[SegmentData]) -> dict[str, float]:
        """The teacher's columns of an update's metrics: its term as it entered the loss
        (lambda included, per slot, as ``policy_loss``), the mean lambda, the greedy
        agreement and the mean KL per acting step (:meth:`BatchedTeacher.report`)."""
        assert self.teacher is not None
        term = lam = 0.0
        for d in kept:
            if d.teacher_logprobs is None or d.kl_weights is None or d.logits is None:
                continue
            with torch.no_grad():
                term += float((self.teacher.terms(d.teacher_logprobs, d.logits)
                               * d.kl_weights).sum())
            lam += float(d.kl_weights.mean()) / len(kept)
        return {"teacher_loss": term / float(self.run_batch), "kl_weight": lam,
                **self.teacher.report()}

    def drop_episodes(self, segments: list[SegmentData], window: list[torch.Tensor],
                      dropped: list[tuple[int, int]]) -> list[torch.Tensor]:
        """``flush_partial_window = false``: the window's segment losses without the steps
        of the ``dropped`` (slot, episode number) episodes, those that ended before the
        window's last segment (the reference worker empties such a partial window at done,
        with no adaptive update). The inner steps they took stay as taken, as there. The
        segments' step weights are narrowed in place, so PPO's later passes drop them too."""
        out = []
        for d, total in zip(segments, window, strict=True):
            assert d.episodes is not None and d.logits is not None and d.values is not None
            gone = np.zeros(d.episodes.shape, bool)
            for s, ep in dropped:
                gone[:, s] |= d.episodes[:, s] == ep
            if not gone.any():
                out.append(total)
                continue
            keep = torch.from_numpy(~gone).to(self.device, d.values.dtype)
            weights: list[torch.Tensor | None] = [keep if w is None else w * keep
                                                  for w in d.weights[:-1]]
            d.weights = [*weights, d.weights[-1]]
            if d.kl_weights is not None:
                d.kl_weights = d.kl_weights * keep
            out.append(self.segment_loss(d.logits, d.values, d)[0])
        return out

    def replay_window(self, state: Any, kept: list[SegmentData]) -> np.ndarray:
        """One more PPO pass over a window: its K segments recomputed from the window's
        start state under the current phi, the inner updates redone with the surrogate
        against the acting log-probs and the first pass's returns and advantages, then
        one Adam step. Returns the pass's (policy, value, entropy) sums per run."""
        cfg = self.cfg
        params = self.params()  # packed runs stack the members' leaves anew
        adapted: Adapted = {}
        window: list[torch.Tensor] = []
        sums = np.zeros((len(self.run_slices()), 3))
        for d in kept:
            total, runs, mine, rec, adapted, state = self.replay_segment(params, adapted,
                                                                         state, d)
            window.append(total)
            sums += [[float(r.policy.detach()), float(r.value.detach()),
                      float(r.entropy.detach())] for r in runs]
            if d.live is not None:
                adapted = rec.inner_factors(mine.total, adapted, cfg.alpha,
                                            create_graph=cfg.second_order, weights=d.live)
        self.step_optimizer(torch.stack(window).sum() / self.run_batch)
        return sums


@dataclass
class SegmentData:
    """A segment's inputs and loss constants: for its loss, and for replaying it in a PPO
    pass after the first (``views`` to ``done_at`` are kept only then)."""

    views: list[torch.Tensor]
    """Per step, (B,) view index of each slot's observation."""
    targets: list[torch.Tensor]
    """Per step, (B,) view index of each slot's target."""
    starts: list[torch.Tensor]
    """Per step, (B,) bool: the slot's state is zeroed before the step (a new episode)."""
    done_at: list[torch.Tensor | None]
    """Per step, (B,) bool where the step ended some slot's episode (theta_s <- phi)."""
    actions: torch.Tensor
    """(N, B) actions taken."""
    returns: torch.Tensor
    """(N, B) discounted returns (masked GAE of the acting pass, kept for later passes)."""
    advantages: torch.Tensor
    """(N, B) GAE advantages (ditto)."""
    weights: list[torch.Tensor | None]
    """Step weightings of the loss: one per run (None: every step), then the slots'
    current episodes (the inner step's loss)."""
    old_logprobs: torch.Tensor | None
    """(N, B) log pi_old(a_t) of the acting theta_s (base_loss 'ppo'), else None."""
    teacher_logprobs: torch.Tensor | None = None
    """(N, B, A) the curriculum teacher's log-probs, or None."""
    kl_weights: torch.Tensor | None = None
    """(N, B) the KL prior's lambda per step."""
    live: torch.Tensor | None = None
    """(B,) the inner step's slot weights after this segment (None: no inner step)."""
    episodes: np.ndarray | None = None
    """(N, B) the number of the episode each step belongs to (slot_episode)."""
    logits: torch.Tensor | None = None
    """(N, B, A) the acting pass's logits, with the graph (a window-end reweighting)."""
    values: torch.Tensor | None = None
    """(N, B) the acting pass's values, with the graph (ditto)."""


def segment_advantages(values: torch.Tensor, rewards: np.ndarray, ends: np.ndarray,
                       v_next: torch.Tensor, lc: Any, end_values: np.ndarray | None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """(returns, advantages) (T, B) of a segment of lock-step steps: masked GAE
    bootstrapped with V(s_next) ``v_next`` (B,) where the last step did not end the slot's
    episode, in the values' dtype and device."""
    bootstrap = np.where(ends[-1], 0.0, v_next.to("cpu", torch.float64).numpy())
    ret, adv = gae_returns(rewards, values.detach().to("cpu", torch.float64).numpy(),
                           bootstrap, ends, lc.gamma, lc.tau, end_values)
    return (torch.from_numpy(ret).to(values.device, values.dtype),
            torch.from_numpy(adv).to(values.device, values.dtype))


def segment_losses(logits: torch.Tensor, values: torch.Tensor, actions: torch.Tensor,
                   returns: torch.Tensor, advantages: torch.Tensor, lc: Any,
                   weights: list[torch.Tensor | None],
                   old_logprobs: torch.Tensor | None = None, clip_coef: float = 0.2
                   ) -> list[LossTerms]:
    """The segment loss once per step weighting in ``weights``: L_AC, or PPO's clipped
    surrogate against ``old_logprobs`` (see :func:`~geonav.policy.losses.policy_value_terms`)."""
    return [policy_value_terms(logits, values, actions, returns, advantages, lc, weights=w,
                               old_log_probs=old_logprobs, clip_coef=clip_coef)
            for w in weights]


def segment_terms(logits: torch.Tensor, values: torch.Tensor, actions: torch.Tensor,
                  rewards: np.ndarray, ends: np.ndarray, v_next: torch.Tensor, lc: Any,
                  end_values: np.ndarray | None, weights: list[torch.Tensor | None]
                  ) -> list[LossTerms]:
    """L_AC of a segment of lock-step steps (T, B), once per step weighting in ``weights``
    (None: every step): masked GAE bootstrapped with V(s_next) ``v_next`` (B,) where the
    last step did not end the slot's episode."""
    ret_t, adv_t = segment_advantages(values, rewards, ends, v_next, lc, end_values)
    return segment_losses(logits, values, actions, ret_t, adv_t, lc, weights)


GRAM_MAX_VIEWS = 8192
"""Above this many views the (C, C) Gram matrix is not built (dense factors instead)."""


def gram_matrix(table: torch.Tensor | None) -> torch.Tensor | None:
    """table @ table.T of the frozen feature table (the view embeddings' factors look their
    inner products up instead of multiplying (B, R, F) inputs), or None when too large."""
    if table is None or table.shape[0] > GRAM_MAX_VIEWS:
        return None
    return table @ table.T


def values_dtype(trainer: BatchedTrainer) -> torch.dtype:
    return next(trainer.model.parameters()).dtype


__all__ = ["BatchedISARTrainer", "SegmentData", "clear_slots", "segment_advantages",
           "segment_losses", "segment_terms", "gram_matrix"]
