"""The batched engine's trainer machinery and its synchronous A3C (A2C form).

:class:`BatchedTrainer` is an :class:`~geonav.policy.a3c.A3CTrainer` whose training loop
steps B episodes in lock-step in this process (a :class:`~geonav.vecenv.LatticeVecEnv`)
instead of running worker processes; everything else is the A3C trainer's own: the run
folder (config.json, metrics.csv with the same columns, checkpoints/ in the same format,
learning_curve.png), resume, callbacks, the episode budget and checkpoint schedule. So
``geonav eval``, ``geonav fly`` and the experiment reports read its runs unchanged.

:class:`BatchedA3CTrainer`, per update (ALGORITHMS.md (a) in synchronous form):

1. act ``t_max`` steps in every slot without autograd (slots that finish start a new
   episode at once, with a zero state), the image part of the network evaluated once per
   distinct view (:class:`~geonav.policy.batched.core.ActingTables`);
2. recompute the rollout with the graph in one call from the stored start state, the
   views encoded once per distinct view (:func:`~geonav.policy.batched.core.sequence_forward`);
3. masked GAE (:func:`~geonav.policy.losses.gae_returns`: bootstrap V(s_T) for live
   slots, 0 at episode ends), L_AC per slot (:func:`~geonav.policy.losses.policy_value_terms`)
   averaged over the B slots, so one update's gradient has the scale of one worker's;
4. clip the norm to ``max_grad_norm`` and take one Adam step.

With B = 1 and a rollout inside one episode this is exactly the reference worker's update
(``tests/test_batched_a3c.py``). Records are written after the update of the rollout in
which an episode ended, with that update's loss figures. A resumed run restores the
weights, Adam, the episode count and the random streams; episodes in flight at the
checkpoint are not saved, so every slot starts a new episode.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from geonav.errors import ConfigError
from geonav.policy.a3c import A3CTrainer, TrainResult
from geonav.policy.batched.core import (
    ActingTables,
    Adapted,
    Params,
    Recorder,
    check_supported,
    core_step,
    encode_slots,
    encoder_weights,
    reset_state,
    sample_actions,
    sequence_forward,
)
from geonav.policy.callbacks import Callback
from geonav.policy.evaluation import spl
from geonav.policy.isar import check_prev_view, teacher_record
from geonav.policy.losses import LossTerms, gae_returns, policy_value_terms
from geonav.policy.model import State
from geonav.policy.optim import warm_up_lr
from geonav.vecenv import LatticeVecEnv, StepResult

DEFAULT_BATCH = 16
"""Slots per run: the order of the paper's and SAVN's worker counts, so a run's updates
per episode stay comparable to multi-worker A3C."""


def resolve_device(device: str | torch.device | None) -> torch.device:
    """'cpu' or 'cuda[:i]' as a torch device; CUDA is refused when torch sees no GPU."""
    try:
        dev = torch.device(device or "cpu")
    except RuntimeError as err:
        raise ConfigError(f"device must be 'cpu' or 'cuda', not {device!r}") from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was asked for, but torch sees no GPU "
                          f"(torch {torch.__version__}, CUDA build "
                          f"{torch.version.cuda or 'none'}); use --device cpu")
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"device must be 'cpu' or 'cuda', not {device!r}")
    return dev


@dataclass
class RolloutBatch:
    """T steps of B slots, stored for the recompute with graph."""

    start_state: State
    view_idx: torch.Tensor
    """(T, B) view index of the observation at each step."""
    target_idx: torch.Tensor
    """(T, B) view index of the slot's target at each step."""
    actions: torch.Tensor
    """(T, B) long."""
    rewards: np.ndarray
    """(T, B) float64."""
    ends: np.ndarray
    """(T, B) bool: the step ended the slot's episode."""
    starts: torch.Tensor
    """(T, B) bool: the step began a new episode (state zeroed before it)."""
    bootstrap: np.ndarray
    """(B,) V(s_T) after the last step (0 where it ended the episode)."""
    end_values: np.ndarray | None = None
    """(T, B) V(s) bootstrapped at truncations (``bootstrap_on_truncation``), else None."""
    logprobs: torch.Tensor | None = None
    """(T, B) log pi(a_t) while acting (PPO)."""
    values: torch.Tensor | None = None
    """(T, B) V(s_t) while acting (PPO)."""
    step_states: State | None = None
    """The recurrent state fed to each step while acting, ((T, B, H), (T, B, H), (T, B, A))
    (``collect(keep_states=True)``: PPO's ``seq_len`` chunks start from them)."""


class BatchedTrainer(A3CTrainer):
    """The batched engine (see the module docstring); arguments as :class:`A3CTrainer`,
    plus ``batch`` (B, slots stepped together) and ``device`` ('cpu' or 'cuda').

    ``cfg.workers`` is recorded but not used: the engine runs in one process with
    ``cfg.torch_threads`` threads (parallelism comes from running several processes).
    ``prev_view`` (a :class:`geonav.policy.teacher.PrevViewSpec`, the curriculum's
    option B) feeds the network's extra input slot the view at each slot's cell at the
    previous altitude, while acting and in the recompute with graph (A3C, PPO; ISAR and
    SAVN take it as their own argument); without one the slot is zero-filled.
    """

    engine = "batched"
    prev_view_spec: Any = None
    """The curriculum's option B source (:class:`geonav.policy.teacher.PrevViewSpec`):
    the extra input slot gets the view at the slot's cell at the previous altitude."""
    per_slot_parameters = False
    """True for learners with stacked per-slot parameters (needs a frozen encoder)."""

    def __init__(self, env_factory: Any, net_cfg: Any = None, cfg: Any = None, *,
                 batch: int = DEFAULT_BATCH, device: str | torch.device | None = "cpu",
                 **kwargs: Any) -> None:
        if batch < 1:
            raise ConfigError(f"batch must be >= 1, got {batch}")
        self.batch = int(batch)
        self.run_batch = self.batch
        """Slots of one run (losses are averaged over them); a packed driver's ``batch`` is
        the runs' slots together (:mod:`geonav.policy.batched.packed`)."""
        self.device = resolve_device(device)
        kwargs.pop("mp_context", None)
        if kwargs.get("prev_view") is not None:
            self.prev_view_spec = kwargs["prev_view"]
        kwargs.pop("prev_view", None)
        super().__init__(env_factory, net_cfg, cfg, **kwargs)
        check_prev_view(self.net_cfg, self.prev_view_spec)
        check_supported(self.model, per_slot_parameters=self.per_slot_parameters)
        # Adam state follows the parameters to the device (load_state_dict casts it).
        opt_state = self.optimizer.state_dict()
        self.model.to(self.device)
        self.params_list: list[torch.Tensor] = list(self.model.parameters())
        for m in self.aux.values():
            m.to(self.device)
            self.params_list += list(m.parameters())
        self.optimizer = self.build_optimizer(self.params_list)
        self.optimizer.load_state_dict(opt_state)
        self.on_gradients: Any = None
        """Called with the unclipped gradients of every update (tests, meta-training)."""

    # -- hooks of A3CTrainer -------------------------------------------------------------
    def build_optimizer(self, params: list[torch.Tensor]) -> torch.optim.Optimizer:
        cfg = self.cfg
        return torch.optim.Adam(params, lr=cfg.lr, betas=cfg.adam_betas, eps=cfg.adam_eps,
                                amsgrad=cfg.amsgrad, fused=cfg.fused or None)

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d["engine"] = {"name": self.engine, "batch": self.batch, "device": str(self.device),
                       "torch_threads": self.cfg.torch_threads,
                       "workers": "unused (one process)"}
        d.pop("mp_context", None)
        if self.prev_view_spec is not None:  # ISAR and SAVN write theirs (KL teacher too)
            d["teacher"] = teacher_record(None, self.prev_view_spec)
        return d

    def save(self, path: Any, episodes: int, rng: dict[str, Any] | None = None) -> Any:
        from geonav.policy.checkpoint import save_checkpoint

        cpu = {k: v.detach().cpu() for k, v in self.model.state_dict().items()}
        return save_checkpoint(path, cpu, self.checkpoint_meta(episodes),
                               self.optimizer.state_dict(), rng,
                               {name: {k: v.detach().cpu() for k, v in m.state_dict().items()}
                                for name, m in self.aux.items()} or None)

    def evaluate_now(self, cbs: list[Callback], result: TrainResult) -> dict[str, Any]:
        """The trainer's periodic evaluation (the reference per-step evaluator, at the same
        episode interval as the async engine, so evaluation e* compare), on a CPU copy."""
        if self.device.type == "cpu":
            return super().evaluate_now(cbs, result)
        import copy

        live = self.model
        self.model = copy.deepcopy(live).cpu()
        try:
            return super().evaluate_now(cbs, result)
        finally:
            self.model = live

    def _train_inline(self, cbs: list[Callback], result: TrainResult) -> None:
        self._train_batched(cbs, result)

    def _train_workers(self, cbs: list[Callback], result: TrainResult) -> None:
        self._train_batched(cbs, result)

    # -- state of the engine --------------------------------------------------------------
    def params(self) -> Params:
        return dict(self.model.named_parameters())

    def make_venv(self) -> LatticeVecEnv:
        return LatticeVecEnv(self.env, self.batch)

    def _setup(self) -> None:
        self.venv = self.make_venv()
        self.rng = np.random.default_rng(self.cfg.seed + 7919 * self.start_episode)
        self.venv.seed(self.cfg.seed + 7919 * self.start_episode)
        st = self.rng_state
        if st is not None and st.get("engine") == "batched":
            torch.set_rng_state(st["torch"])
            self.rng.bit_generator.state = st["numpy"]
            self.venv.np_random.bit_generator.state = st["env"]
        self.reset_venv()
        dtype = next(self.model.parameters()).dtype
        self.prev_table = self.prev_images = None
        if self.prev_view_spec is not None:
            if not self.net_cfg.prev_view_input:
                raise ConfigError("the previous-altitude view input needs a network with the "
                                  "extra slot (NetConfig.prev_view_input = true)")
            # the same lattice at the previous altitude: the same view indices
            prev_env = LatticeVecEnv(self.prev_view_spec.env_factory(), 1)
            if self.frozen is not None:
                self.prev_table = prev_env.feature_table(self.frozen).to(self.device, dtype)
            else:  # the trainable CNN encodes them as it does the current views
                self.prev_images = torch.from_numpy(prev_env.image_table()).to(self.device)
        if self.frozen is not None:
            self.table = self.venv.feature_table(self.frozen).to(self.device, dtype)
            self.images = None
        else:
            self.table = None
            self.images = torch.from_numpy(self.venv.image_table()).to(self.device)
        b = self.batch
        self.state: State = tuple(x.to(self.device, dtype)  # type: ignore[assignment]
                                  for x in self.model.initial_state(b))
        self.fresh = torch.ones(b, dtype=torch.bool, device=self.device)
        self.t_episode = np.full(b, time.perf_counter())
        self.slot_episode = self.start_episode + 1 + np.arange(b)
        """The number of each slot's current episode in start order (schedules by episode,
        such as the curriculum teacher's lambda, read it)."""
        self.next_episode = self.start_episode + 1 + b

    def reset_venv(self) -> None:
        """A new episode in every slot (meta-training draws its task visits' starts)."""
        self.venv.reset()

    def rng_snapshot(self) -> dict[str, Any]:
        return {"engine": "batched", "torch": torch.get_rng_state(),
                "numpy": self.rng.bit_generator.state,
                "env": self.venv.np_random.bit_generator.state}

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        """(n, F) features of view indices: the frozen table, or the CNN (with graph)."""
        if self.table is not None:
            return self.table[rows]
        assert self.images is not None
        return self.model.features(self.images[rows])

    def slot_views(self, params: Params, adapted: Adapted | None, rows: torch.Tensor,
                   rec: Recorder | None = None, slots: torch.Tensor | None = None, *,
                   prev: bool = False) -> torch.Tensor:
        """(n, F) features of one view per slot under the slots' adapted weights (ISAR,
        SAVN): ``rows`` (n,) the views of ``slots`` (default: all B, in order). The frozen
        table's rows; or the trainable CNN, each slot's view encoded with its own weights
        (:func:`~geonav.policy.batched.core.encode_slots`, with graph), the weights
        recorded in ``rec`` for the inner gradients. ``prev``: the previous-altitude views
        at those rows instead (the extra slot's input)."""
        table, images = (self.prev_table, self.prev_images) if prev else \
            (self.table, self.images)
        if table is not None:
            return table[rows]
        assert images is not None and self.model.encoder is not None
        w = encoder_weights(params, adapted, self.batch)
        if rec is not None:
            rec.add_encoder(w)
        if slots is not None:
            w = {k: v[slots] for k, v in w.items()}
        return encode_slots(self.model.encoder, w, images[rows].unsqueeze(1))[:, 0]

    def slot_prev(self, params: Params, adapted: Adapted | None, rows: torch.Tensor,
                  rec: Recorder | None = None) -> torch.Tensor | None:
        """(B, F) previous-altitude view features of the slots' cells ``rows`` under their
        adapted weights (:meth:`slot_views`), or None (the extra slot zero-filled)."""
        if self.prev_table is None and self.prev_images is None:
            return None
        return self.slot_views(params, adapted, rows, rec, prev=True)

    def slot_targets(self, params: Params, adapted: Adapted | None, target_idx: torch.Tensor,
                     rec: Recorder | None, last: torch.Tensor | None,
                     fresh: torch.Tensor | None = None) -> torch.Tensor:
        """(B, F) target features as :meth:`slot_views`. With the trainable CNN each slot's
        target is encoded once per weights: ``last`` (this step's weights, or None) is
        kept for the slots that do not begin a new episode at this step (``fresh``,
        default the slots' current flags; a replay passes the flags it kept)."""
        if self.table is not None or last is None:
            return self.slot_views(params, adapted, target_idx, rec)
        fresh = self.fresh if fresh is None else fresh
        if not bool(fresh.any()):
            return last
        idx = fresh.nonzero()[:, 0]
        return last.index_put((idx,), self.slot_views(params, adapted, target_idx[idx], rec,
                                                      idx))

    def prev_features(self, rows: torch.Tensor) -> torch.Tensor | None:
        """(n, F) features of the previous-altitude views at view indices, or None (the
        extra slot, when the network has one, is zero-filled)."""
        if self.prev_images is not None:
            return self.model.features(self.prev_images[rows])
        return None if self.prev_table is None else self.prev_table[rows]

    def acting_tables(self) -> ActingTables:
        return ActingTables(self.params(), self.net_cfg.embed_dim, self.venv.n_views,
                            self.features,
                            None if self.prev_table is None and self.prev_images is None
                            else self.prev_features)

    def run_slices(self) -> list[slice]:
        """The slot columns of each run: one run here, R in a packed driver."""
        return [slice(None)]

    def run_masks(self, like: torch.Tensor) -> list[torch.Tensor | None]:
        """Per-run step weights shaped like ``like`` (T, B): [None] for one run; one 0/1
        mask of each run's slot columns when packed (per-run losses and figures)."""
        slices = self.run_slices()
        if len(slices) == 1:
            return [None]
        cols = torch.arange(like.shape[1], device=like.device)
        return [torch.zeros_like(like).index_fill_(1, cols[s], 1.0) for s in slices]

    def run_rngs(self) -> list[np.random.Generator]:
        """The random streams of the runs, in slot order (one here; one per packed run)."""
        return [self.rng]

    def view_rows(self, view_idx: torch.Tensor, target_idx: torch.Tensor,
                  slots: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(table rows to encode, their positions for view_idx, for target_idx): each
        distinct view once (``slots``: the columns' slots, for packed runs)."""
        uniq, inv = torch.unique(torch.cat([view_idx.flatten(), target_idx.flatten()]),
                                 return_inverse=True)
        n = view_idx.numel()
        return uniq, inv[:n].view_as(view_idx), inv[n:].view_as(target_idx)

    def slot_indices(self) -> tuple[torch.Tensor, torch.Tensor]:
        v = torch.from_numpy(self.venv.view_index).to(self.device)
        t = torch.from_numpy(self.venv.target_index).to(self.device)
        return v, t

    # -- the loop -------------------------------------------------------------------------
    def _train_batched(self, cbs: list[Callback], result: TrainResult) -> None:
        threads = torch.get_num_threads()
        torch.set_num_threads(self.cfg.torch_threads)
        try:
            self._setup()
            go_on = True
            while go_on and self.episodes_done < self.cfg.episodes:
                before = self.episodes_done
                finals, stats = self.update()
                left = self.cfg.episodes - self.episodes_done
                for f in finals[:left]:
                    if not self._on_record(self.record(f, stats), cbs, result,
                                           self.rng_snapshot):
                        go_on = False
                self.report_update(stats, cbs, result)
                self.after_update(before, cbs)
            self._final_rng = self.rng_snapshot()
        finally:
            torch.set_num_threads(threads)

    n_updates: int = 0
    """Optimiser updates of this call of :meth:`train` (SB3's ``train/n_updates``)."""

    reports_updates = True
    """This engine calls the callbacks' ``on_update`` once per update (its losses are
    logged per update, as SB3 does)."""

    def report_update(self, stats: Any, cbs: list[Callback], result: TrainResult) -> None:
        """One update done: ``on_update`` of the callbacks with its loss figures, the update
        count and the run's env steps so far (after the update's finished episodes)."""
        self.n_updates += 1
        if not isinstance(stats, dict):
            return
        row = {**stats, "n_updates": self.n_updates, "env_steps": self.total_env_steps(result)}
        for cb in cbs:
            hook = getattr(cb, "on_update", None)  # duck-typed callbacks too
            if hook is not None:
                hook(row)

    def after_update(self, before: int, cbs: list[Callback]) -> None:
        """Called after an update's records (``before``: episodes before it); meta-training
        writes its checkpoints here, at batch boundaries."""

    def record(self, f: dict[str, Any], stats: dict[str, float]) -> dict[str, Any]:
        """The metrics row of a finished episode (the A3C trainer's columns)."""
        now = time.perf_counter()
        s = f["slot"]
        rec = {"episode": self.episodes_done + 1, "worker": s, "task": f["task"],
               "task_index": f["task_index"], "return": f["return"], "length": f["length"],
               "success": f["success"],
               "spl": spl(f["success"], f["shortest_path"], f["length"]),
               "collisions": f["collisions"], "shortest_path": f["shortest_path"],
               "env_steps": f["length"], "wall_s": now - float(f.get("t0", now)), **stats}
        return rec

    def env_step(self, actions: torch.Tensor) -> StepResult:
        """Step the vector env, note the finished episodes' start times."""
        res = self.venv.step(actions.cpu().numpy())
        now = time.perf_counter()
        for f in res.final:
            s = f["slot"]
            f["t0"] = float(self.t_episode[s])
            f["started_as"] = int(self.slot_episode[s])
            self.t_episode[s] = now
            self.slot_episode[s] = self.next_episode
            self.next_episode += 1
        self.fresh = torch.from_numpy(res.done).to(self.device)
        return res

    def update(self) -> tuple[list[dict[str, Any]], dict[str, float]]:
        """One rollout and its update(s); (finished episodes, loss figures)."""
        raise NotImplementedError

    def step_optimizer(self, loss: torch.Tensor) -> None:
        """Backward, show the gradients, clip, step."""
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.apply_gradients()

    def apply_gradients(self) -> None:
        for p in self.params_list:  # unused parameters step with a zero gradient, as async
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        if self.on_gradients is not None:
            self.on_gradients([p.grad for p in self.params_list])
        if self.cfg.max_grad_norm:
            nn.utils.clip_grad_norm_(self.params_list, self.cfg.max_grad_norm)
        warm_up_lr(self.optimizer, self.cfg.lr, self.cfg.lr_warmup)
        self.optimizer.step()

    # -- rollouts (A3C and PPO) -------------------------------------------------------------
    def collect(self, t_max: int, keep_policy: bool = False, keep_states: bool = False
                ) -> tuple[RolloutBatch, list[dict[str, Any]]]:
        """Act ``t_max`` steps in every slot without autograd (``keep_states``: also the
        recurrent state each step was acted from)."""
        params, e = self.params(), self.net_cfg.embed_dim
        boot_trunc = self.cfg.loss.bootstrap_on_truncation
        finals: list[dict[str, Any]] = []
        with torch.no_grad():
            tables = self.acting_tables()
            start_state = reset_state(self.state, self.fresh)
            state = start_state
            vis, tis, acts, starts, lps, vals = [], [], [], [], [], []
            kept: list[State] = []
            rewards = np.zeros((t_max, self.batch))
            ends = np.zeros((t_max, self.batch), bool)
            end_values = np.zeros((t_max, self.batch)) if boot_trunc else None
            for t in range(t_max):
                vi, ti = self.slot_indices()
                starts.append(self.fresh)
                state = reset_state(state, self.fresh)
                if keep_states:
                    kept.append(state)
                logits, value, state = core_step(params, e, state, pre=tables.pre(vi, ti))
                a = sample_actions(logits, self.rng).to(self.device)
                if keep_policy:
                    lps.append(torch.log_softmax(logits, -1).gather(1, a[:, None])[:, 0])
                    vals.append(value)
                res = self.env_step(a)
                if end_values is not None and res.truncated.any():
                    fv = torch.from_numpy(res.final_view).to(self.device)
                    _, v_end, _ = core_step(params, e, state, pre=tables.pre(fv, ti))
                    end_values[t] = np.where(res.truncated, v_end.cpu().numpy(), 0.0)
                vis.append(vi)
                tis.append(ti)
                acts.append(a)
                rewards[t] = res.rewards
                ends[t] = res.done
                finals += res.final
            vi, ti = self.slot_indices()
            _, v_next, _ = core_step(params, e, state, pre=tables.pre(vi, ti))
            bootstrap = np.where(ends[-1], 0.0, v_next.to("cpu", torch.float64).numpy())
        self.state = state
        batch = RolloutBatch(start_state, torch.stack(vis), torch.stack(tis), torch.stack(acts),
                             rewards, ends, torch.stack(starts), bootstrap, end_values,
                             torch.stack(lps) if keep_policy else None,
                             torch.stack(vals) if keep_policy else None,
                             tuple(torch.stack(x) for x in zip(*kept, strict=True))  # type: ignore[arg-type]
                             if keep_states else None)
        return batch, finals

    def recompute(self, ro: RolloutBatch, slots: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """logits (T, B', A) and values (T, B') of a rollout with the graph, each distinct
        view's image part evaluated once (``slots``: a subset of the slots)."""
        view_idx, target_idx, starts = ro.view_idx, ro.target_idx, ro.starts
        state = ro.start_state
        if slots is not None:
            view_idx, target_idx, starts = view_idx[:, slots], target_idx[:, slots], \
                starts[:, slots]
            state = (state[0][slots], state[1][slots], state[2][slots])
        rows, vinv, tinv = self.view_rows(view_idx, target_idx, slots)
        logits, values, _ = sequence_forward(
            self.params(), self.net_cfg.embed_dim, self.features(rows), vinv, tinv, state,
            starts, self.prev_features(rows))
        return logits, values

    def advantages(self, ro: RolloutBatch, values: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """Masked GAE of a rollout: (returns, advantages), (T, B) in the values' dtype."""
        lc = self.cfg.loss
        v = values.detach().to("cpu", torch.float64).numpy()
        ret, adv = gae_returns(ro.rewards, v, ro.bootstrap, ro.ends, lc.gamma, lc.tau,
                               ro.end_values)
        return (torch.from_numpy(ret).to(self.device, values.dtype),
                torch.from_numpy(adv).to(self.device, values.dtype))


def loss_stats(terms: LossTerms, steps: int) -> dict[str, float]:
    """The loss columns of the metrics rows from an update's terms (per-slot averages)."""
    return {"policy_loss": float(terms.policy.detach()), "value_loss": float(terms.value.detach()),
            "entropy": float(terms.entropy.detach()) / max(steps, 1)}


class BatchedA3CTrainer(BatchedTrainer):
    """Synchronous batched A3C (see the module docstring)."""

    algorithm = "a3c"
    config_key = "a3c"

    def a3c_loss(self, ro: RolloutBatch) -> list[LossTerms]:
        """L_AC of a rollout averaged over a run's slots (graph kept), one per run."""
        logits, values = self.recompute(ro)
        returns, advantages = self.advantages(ro, values)
        b = float(self.run_batch)
        out = []
        for s in self.run_slices():
            t = policy_value_terms(logits[:, s], values[:, s], ro.actions[:, s],
                                   returns[:, s], advantages[:, s], self.cfg.loss)
            out.append(LossTerms(t.total / b, t.policy / b, t.value / b, t.entropy / b))
        return out

    def update(self) -> tuple[list[dict[str, Any]], Any]:
        ro, finals = self.collect(self.cfg.t_max)
        terms = self.a3c_loss(ro)
        self.step_optimizer(torch.stack([t.total for t in terms]).sum())
        stats = [loss_stats(t, ro.view_idx.shape[0]) for t in terms]
        return finals, stats[0] if len(stats) == 1 else stats


__all__ = ["BatchedTrainer", "BatchedA3CTrainer", "RolloutBatch", "resolve_device",
           "DEFAULT_BATCH"]
