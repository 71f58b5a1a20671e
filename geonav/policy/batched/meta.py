"""Meta-training (Eq. 1, ALGORITHMS.md (d)) on the batched engine.

A meta-iteration takes the next B meta-tasks in cyclic order and runs E episodes of the
base algorithm on each (``episodes_per_task``), all B at once:
slot j of the round is pinned to task j of the batch and starts from psi. Task i's
gradient g_i is what the reference (:class:`~geonav.policy.meta.MetaTrainer` and its
``TaskRunner``) defines; then
psi <- psi - eta sum_i g_i (:func:`~geonav.policy.meta.meta_step`: SGD, or Adam as
``meta_optimizer``; ``meta_max_grad_norm`` clips the sum). Checkpoints are written after
the meta update that reaches every ``checkpoint_every`` episodes, as the reference does,
so a resume starts at a batch boundary and goes on with the cyclic order.

* **SAVN base** (:class:`BatchedMetaSAVN`, on
  :class:`~geonav.policy.batched.savn.BatchedSAVNTrainer`'s episode-synchronous round):
  g_i is the episode's exact meta-gradient w.r.t. its initial parameters (= psi, and
  Lambda). With E = 1 the slots run psi itself (the reference's in-task Adam never
  changes a task gradient: its step follows the only episode and is discarded), and one
  backward of the round gives sum_i g_i. With E > 1 each slot carries its own phi^i of the
  policy and of Lambda, run-stacked (B, ...) in the model's layout as packed runs of one
  slot each (:class:`~geonav.policy.batched.core.RunParams`; the trainable CNN per slot
  too), and its own fresh in-task Adam (:class:`SlotAdam`, below): one SAVN round per
  episode of the visits, each slot's meta-gradient w.r.t. its phi^i added to g_i,
  clipped per slot to ``max_grad_norm`` and stepped by its Adam, as the reference's
  TaskRunner does. In both, the trainable CNN adapts per slot as in single-task SAVN.
* **ISAR base** (:class:`BatchedMetaISAR`): each slot carries its own copy of the
  parameters, phi^i, stacked along a leading dim (B, ...) (per-slot weights of every
  linear map, :func:`~geonav.policy.batched.core.linear`), and its own fresh in-task
  Adam state (:class:`SlotAdam` over the stacked tensors: Adam is elementwise, and a
  step count per slot with only the live slots stepping makes slot j's moments and bias
  corrections exactly a per-task Adam's). With E > 1 the visit's episodes run one after
  another, each from h = 0 on the phi^i and Adam the previous one left (the rounds of
  all slots in lock-step; the starts of a visit's episodes are drawn together, in the
  reference's order). On top of phi^i the interaction policy theta is the exact factored
  per-slot inner update of :mod:`geonav.policy.batched.isar` (N-step segments, inner SGD
  at the first K - 1 segment ends, create_graph = ``second_order``); at each window end
  (K segments, or the episode end) grad_phi^i of the window's summed L_adapt is added,
  unclipped, to g_i, clipped per slot to ``max_grad_norm`` and stepped by the slot's
  Adam; theta <- phi^i, h detached. g_i = sum over windows of those gradients (first
  order in psi: d phi^i / d psi is taken as I). With the trainable CNN, phi^i is
  run-stacked in the model's layout instead (every slot's row in every window, each
  slot's views encoded with its own adapted CNN weights, its target once per segment),
  and the window gradients come from autograd: the cost notes below are the frozen
  encoder's.
* **A3C base** (:class:`BatchedMetaA3C`): the same with windows of one segment of
  ``t_max`` steps and no inner step: one per-task Adam step per rollout, g_i the sum of
  the rollout gradients (ISAR with K = 1 is the A3C worker's update exactly).

Cost (``bench/bench_meta_speed.py``, ``shared/notes/batched-training.md``): every slot
reads its own weights each step and its own Adam moments each window, so the per-slot
part does not amortise with B. What keeps it small:

* no parameter has a gradient edge in the graph. A per-slot weight enters the loss only
  through recorded products y = x W_s (:class:`~geonav.policy.batched.core.SlotProduct`)
  and, in second order, through the backward products g_x = g_y W_s^T that an inner step
  takes with the graph; its gradient is assembled per window from those records in one
  batched product per layer (``layer_grads``, ``back_grads``), not as an outer product per
  step and use accumulated by autograd (most of a second-order window before);
* before a task's first in-task Adam step phi^i = psi in every slot, so the window runs
  psi's shared weights (:class:`~geonav.policy.batched.core.AtPsi`): one matrix product
  over the B rows per layer, with the same per-slot gradients from the records;
* a window runs on the slots live at its start only (their phi^i rows copied), so slots
  whose episodes ended do not cost rows while they wait for the others;
* the view embeddings (their inputs are constant feature rows) are evaluated without
  graph, as a table of every view of the slot's task per window where that is cheaper
  than one row per step; their outputs become leaves, their weight gradients one batched
  product sum_t x_t^T u_t per window;
* :class:`SlotAdam` steps every live slot's rows in one call of torch's fused Adam.

With a frozen encoder the ISAR and A3C bases' per-slot weights are stored transposed,
(B, in, out): x W_s is a row-vector batched product, 5-10x faster on the CPU than W_s x.

All slots start together with h = 0, so their segments and windows fall on the same
global clock as each reference episode's own; a slot whose episode ends waits (its later
steps are masked out, its partial window is flushed at the window end, where its phi^i
has not changed since, so this is the reference's flush at done; with
``flush_partial_window = false`` that slot's partial window is dropped instead, no task
gradient and no Adam step, as the reference worker empties it) until every slot has
finished. ``lr_warmup`` ramps each slot's in-task rate from its own step count, as the
reference's fresh per-visit Adam does. ``tests/test_batched_meta.py`` checks the task
gradients and the meta update of B = 1 and B = 3 tasks (E = 1 and 2; frozen encoder and
trainable CNN; without the flush; with the warm-up) against the reference's in float64 on
forced trajectories.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, ClassVar

import numpy as np
import torch

from geonav.errors import ConfigError
from geonav.policy.batched.core import (
    Adapted,
    AtPsi,
    Params,
    Recorder,
    RunParams,
    back_grads,
    factored_step,
    layer_grads,
    sample_actions,
)
from geonav.policy.batched.isar import gram_matrix, segment_terms, values_dtype
from geonav.policy.batched.meta_parts import (
    SlotAdam,
    ViewBases,
    clip_per_slot,
    psi_layout,
)
from geonav.policy.batched.savn import BatchedSAVNTrainer
from geonav.policy.batched.trainer import BatchedTrainer
from geonav.policy.callbacks import Callback
from geonav.policy.config import A3CConfig, to_dict
from geonav.policy.isar import gradient_path
from geonav.policy.losses import LossTerms
from geonav.policy.meta import TASK_GRADIENT, checkpoint_after_update, meta_step
from geonav.policy.meta_config import PPO_BASE_META, MetaConfig, check_a3c_base
from geonav.policy.model import State, detach_state
from geonav.vecenv import LatticeVecEnv


class MetaRun:
    """What the batched meta-trainers share (mixed in before a batched trainer): the meta
    config, the slots' cyclic task order, the meta optimiser, the run folder's meta
    entries and checkpoints at batch boundaries. B is the meta-batch."""

    config_key = "base"
    base_algo = ""
    base_overrides: ClassVar[dict[str, Any]] = {}
    """Base-config fields the meta run sets (besides its budget, seed and threads)."""
    many_episodes_per_task = False
    """True where E > 1 episodes per task visit are implemented (per-task parameters)."""

    def __init__(self, env_factory: Any, net_cfg: Any, base_cfg: A3CConfig,
                 meta_cfg: MetaConfig | None = None, *, keep_task_grads: bool = False,
                 **kwargs: Any) -> None:
        self.meta_cfg = m = meta_cfg if meta_cfg is not None else MetaConfig()
        if m.episodes_per_task != 1 and not self.many_episodes_per_task:
            raise ConfigError(f"batched meta-training with the {self.base_algo.upper()} base "
                              "runs E = 1 episode per task visit; use engine = 'async' for "
                              "more")
        self.algorithm = f"meta-{self.base_algo}"
        base_cfg = replace(base_cfg, episodes=m.episodes, workers=m.workers, seed=m.seed,
                           checkpoint_every=0, torch_threads=m.torch_threads,
                           **self.base_overrides)
        kwargs.pop("batch", None)
        super().__init__(env_factory, net_cfg, base_cfg, batch=m.batch,  # type: ignore[call-arg]
                         **kwargs)
        self.n_tasks = len(self.env.unwrapped.tasks)  # type: ignore[attr-defined]
        ckpt = self.ckpt  # type: ignore[attr-defined]
        self.meta_updates = int(ckpt.meta.get("meta_updates", 0) if ckpt is not None else 0)
        self.keep_task_grads = keep_task_grads
        self.update_log: list[dict[str, Any]] = []
        """Per meta update, as :attr:`MetaTrainer.update_log` (the batch's tasks; with
        ``keep_task_grads`` psi before and after and the task gradients)."""

    def build_optimizer(self, params: list[torch.Tensor]) -> torch.optim.Optimizer:
        m = self.meta_cfg
        if m.meta_optimizer == "adam":
            return torch.optim.Adam(params, lr=m.meta_lr)
        return torch.optim.SGD(params, lr=m.meta_lr)

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()  # type: ignore[misc]
        d.update({"meta": to_dict(self.meta_cfg), "base_algorithm": self.base_algo,
                  "task_gradient": TASK_GRADIENT[self.base_algo]})
        return d

    def checkpoint_meta(self, episodes: int) -> dict[str, Any]:
        meta = super().checkpoint_meta(episodes)  # type: ignore[misc]
        meta["config"]["meta"] = to_dict(self.meta_cfg)
        meta["config"]["base_algorithm"] = self.base_algo
        meta["meta_updates"] = self.meta_updates
        return meta

    def batch_tasks(self, visits: int) -> np.ndarray:
        """Slot j <- task (visits + j) mod M, visits = episodes so far (a resume goes on)."""
        return ((visits + np.arange(self.batch)) % self.n_tasks).astype(  # type: ignore
            np.int64)

    def make_venv(self) -> LatticeVecEnv:
        self._visits = self.episodes_done // self.meta_cfg.episodes_per_task  # type: ignore
        return LatticeVecEnv(self.env, self.batch,  # type: ignore[attr-defined]
                             slot_tasks=self.batch_tasks(self._visits))

    def next_round(self, visits: int | None = None) -> None:
        """The next B tasks (``visits``: the task visits the round ran; default B)."""
        self._visits += self.batch if visits is None else visits  # type: ignore
        self.venv.slot_tasks = self.batch_tasks(self._visits)  # type: ignore[attr-defined]
        self.reset_venv()  # type: ignore[attr-defined]

    def after_update(self, before: int, cbs: list[Callback]) -> None:
        checkpoint_after_update(self, before, cbs, self.rng_snapshot)  # type: ignore

    def record(self, f: dict[str, Any], stats: dict[str, float]) -> dict[str, Any]:
        rec = super().record(f, stats)  # type: ignore[misc]
        rec["meta_update"] = f["meta_update"]
        return rec

    # -- per-task parameters phi^i (the ISAR and A3C bases; the SAVN base with E > 1) ----
    transposed_slots = True
    """Per-slot 2-D weights stored transposed, (B, in, out), for the recorded products
    (:class:`~geonav.policy.batched.core.SlotProduct`); False: in the model's layout,
    (B, out, in), run-stacked (:class:`~geonav.policy.batched.core.RunParams`, one run a
    slot), their gradients by ordinary autograd."""

    def _setup(self) -> None:
        super()._setup()  # type: ignore[misc]
        self._slots: Any = None
        self._ran = 0
        """Episodes of the last round (its slots move to the next tasks at the next one)."""

    def reset_venv(self) -> None:
        """The round's first episodes. With E > 1 the starts of every episode of the
        visits are drawn here, visit by visit (a task's E episodes in turn, the
        reference's order of draws); a visit's later episodes reset to them."""
        e, venv = self.meta_cfg.episodes_per_task, self.venv  # type: ignore[attr-defined]
        if e == 1:
            venv.reset()
            return
        self._starts = np.array([[venv.draw_start(int(t)) for _ in range(e)]
                                 for t in venv.slot_tasks])                     # (B, E, 2)
        venv.reset(starts=self._starts[:, 0])

    def jobs(self) -> np.ndarray:
        """(B,) episodes of each slot's task visit in this meta-iteration (E, or fewer
        at the end of the budget, as the reference's batches; 0: no task)."""
        e = self.meta_cfg.episodes_per_task
        left = self.cfg.episodes - self.episodes_done  # type: ignore[attr-defined]
        return np.clip(left - e * np.arange(self.batch), 0, e)  # type: ignore[attr-defined]

    def slot_psi(self) -> dict[str, torch.Tensor]:
        """psi by name in the order of ``params_list``: the policy's parameters, then the
        aux modules' (named ``<key>.<name>``: SAVN's learned loss)."""
        d = dict(self.model.named_parameters())  # type: ignore[attr-defined]
        for key, mod in self.aux.items():  # type: ignore[attr-defined]
            d.update({f"{key}.{n}": p for n, p in mod.named_parameters()})
        return d

    def task_parameters(self) -> tuple[dict[str, torch.Tensor], SlotAdam, list[torch.Tensor]]:
        """phi^j <- psi for every slot, stacked (B, ...) leaves (2-D weights (B, in, out)
        with :attr:`transposed_slots`, see :func:`~geonav.policy.batched.core.linear`),
        their fresh Adam and zeroed task gradients. The buffers live across rounds
        (re-allocating B copies of the network and its Adam moments each round costs more
        than filling them)."""
        cfg, b, tr = self.cfg, self.batch, self.transposed_slots  # type: ignore[attr-defined]
        psi = self.slot_psi()
        if self._slots is None:
            phi = {n: torch.empty((b, *p.shape[::-1]) if tr and p.dim() == 2 else
                                  (b, *p.shape), dtype=p.dtype,
                                  device=p.device).requires_grad_()
                   for n, p in psi.items()}
            opt = SlotAdam(list(phi.values()), cfg.lr, cfg.adam_betas, cfg.adam_eps,
                           cfg.amsgrad, cfg.lr_warmup)
            self._slots = (phi, opt, [torch.zeros_like(x) for x in phi.values()])
        phi, opt, task_grads = self._slots
        with torch.no_grad():
            for n, p in psi.items():
                phi[n].copy_((p.t() if tr and p.dim() == 2 else p).unsqueeze(0)
                             .expand_as(phi[n]))
            opt.reset()  # a fresh Adam: step 0, zero moments
            for g in task_grads:
                g.zero_()
        return phi, opt, task_grads

    def psi_layout(self, g: torch.Tensor) -> torch.Tensor:
        """One slot's gradient (or a sum of them) in its parameter's layout."""
        return psi_layout(g) if self.transposed_slots else g

    def task_meta_step(self, task_grads: list[torch.Tensor], n_jobs: int,
                       tasks: list[int]) -> None:
        """psi <- psi - eta * sum_i g_i over the first ``n_jobs`` slots' task gradients
        (``tasks``: their task indices, for the update log)."""
        lay = self.psi_layout
        if self.on_gradients is not None:  # type: ignore[attr-defined]
            self.on_gradients([lay(g[:n_jobs].sum(0)) for g in task_grads])  # type: ignore
        total = [lay(g[:n_jobs].sum(0)) for g in task_grads]
        entry = meta_step(self.optimizer, self.params_list,  # type: ignore[attr-defined]
                          [[lay(g[j]) for g in task_grads] for j in range(n_jobs)]
                          if self.keep_task_grads else [], self.meta_cfg.meta_max_grad_norm,
                          keep=self.keep_task_grads, total=total)
        self.meta_updates += 1
        self.update_log.append({"tasks": tasks, **entry})

    def step_slots(self, grads: list[torch.Tensor], rows: np.ndarray) -> None:
        """The in-task update of the slots ``rows`` with their gradients ``grads``
        ((len(rows), ...) per parameter, unclipped): added to their task gradients g_i,
        clipped per slot to the base's ``max_grad_norm``, one step of each slot's Adam."""
        _, opt, task_grads = self._slots
        if len(rows) == self.batch:  # type: ignore[attr-defined]
            torch._foreach_add_(task_grads, grads)
        else:
            idx = torch.from_numpy(rows).to(grads[0].device)
            for g_i, g in zip(task_grads, grads, strict=True):
                g_i.index_add_(0, idx, g)
        clip_per_slot(grads, self.cfg.max_grad_norm)  # type: ignore[attr-defined]
        opt.step(grads, rows.tolist())



class BatchedMetaSAVN(MetaRun, BatchedSAVNTrainer):
    """Meta-training with the SAVN base on the batched engine (see the module docstring).

    With E = 1 the slots run psi's own parameters and one backward of the round gives
    the sum of the task gradients; with E > 1 each slot runs its own phi^i (run-stacked
    per-slot parameters of the policy and the learned loss, :class:`SlotAdam`), one SAVN
    round per episode of the visits. Args as :class:`~geonav.policy.meta.MetaTrainer`
    with ``algo = 'savn'``.
    """

    base_algo = "savn"
    many_episodes_per_task = True
    transposed_slots = False

    def __init__(self, env_factory: Any, net_cfg: Any, base_cfg: A3CConfig,
                 meta_cfg: MetaConfig | None = None, **kwargs: Any) -> None:
        e = (meta_cfg if meta_cfg is not None else MetaConfig()).episodes_per_task
        self.per_task = e > 1
        """Per-slot phi^i and in-task Adam steps (E > 1)."""
        if not self.per_task:  # the in-task step follows the visit's only episode: unused
            base_cfg = replace(base_cfg, max_grad_norm=0.0)
        self._task: tuple[dict[str, torch.Tensor], SlotAdam, list[torch.Tensor]] | None = None
        self._live = np.ones(0, bool)
        self._round = (0, 1)
        super().__init__(env_factory, net_cfg, base_cfg, meta_cfg, **kwargs)

    # -- the SAVN round's hooks ------------------------------------------------------------
    def params(self) -> Params:
        """psi (E = 1), or the slots' phi^i of the policy, run-stacked (B, ...)."""
        if self._task is None:
            return super().params()
        return RunParams({n: x for n, x in self._task[0].items() if not n.startswith(AUX)})

    def loss_params(self) -> tuple[dict[str, torch.Tensor], int | None]:
        """Lambda shared (E = 1), or the slots' phi^i of the learned loss (vmap dim 0)."""
        if self._task is None:
            return super().loss_params()
        return {n[len(AUX):]: x for n, x in self._task[0].items() if n.startswith(AUX)}, 0

    def round_slots(self) -> np.ndarray:
        return self._live.copy()

    def next_round(self, visits: int | None = None) -> None:
        """The visit's next episode in every slot (E > 1), else the next B tasks."""
        e, rounds = self._round
        if e + 1 < rounds:
            self.venv.reset(starts=self._starts[:, e + 1])
            return
        super().next_round(visits)

    def step_optimizer(self, loss: torch.Tensor) -> None:
        """E = 1: psi <- psi - eta * sum_i g_i (the round's loss is the mean over the B
        slots, so its gradient times B is the sum of the task gradients). E > 1: each
        playing slot's meta-gradient w.r.t. its phi^i goes into g_i and its Adam step."""
        if self._task is not None:
            phi = list(self._task[0].values())
            gs = torch.autograd.grad(loss * self.batch, phi, allow_unused=True)
            rows = np.flatnonzero(self._live)
            idx = torch.from_numpy(rows).to(self.device)
            self.step_slots([(torch.zeros_like(x) if g is None else g)[idx].contiguous()
                             for x, g in zip(phi, gs, strict=True)], rows)
            return
        self.optimizer.zero_grad(set_to_none=True)
        (loss * self.batch).backward()
        total = [torch.zeros_like(p) if p.grad is None else p.grad for p in self.params_list]
        if self.on_gradients is not None:
            self.on_gradients(total)
        entry = meta_step(self.optimizer, self.params_list, [total],
                          self.meta_cfg.meta_max_grad_norm)
        self.meta_updates += 1
        self.update_log.append({"tasks": self._tasks, **entry})

    def update(self) -> tuple[list[dict[str, Any]], dict[str, float]]:
        """One meta-iteration: a SAVN round (E = 1), or E rounds on per-task parameters
        (phi^i and its Adam carried from one to the next), then the meta step."""
        jobs = self.jobs()
        n_jobs = int((jobs > 0).sum())
        self._tasks = self.venv.slot_tasks[:n_jobs].tolist()
        rounds = int(jobs.max())
        if not self.per_task:
            self._live, self._round = jobs > 0, (0, 1)
            finals, stats = super().update()
        else:
            self._task = self.task_parameters()
            finals = []
            try:
                for e in range(rounds):
                    self._live, self._round = jobs > e, (e, rounds)
                    fin, stats = super().update()
                    for f in fin:
                        f["task_episode"] = e
                    finals += fin
            finally:
                self._task = None
            self.task_meta_step(self._slots[2], n_jobs, self._tasks)
            # records in batch order (a task's episodes in turn), as the reference's
            finals.sort(key=lambda f: (f["slot"], f["task_episode"]))
        for f in finals:
            f["meta_update"] = self.meta_updates
        return finals, stats


PRE_TABLE_VIEWS_PER_STEP = 12
"""The window's view-embedding table of every view of the slots' tasks is built when the
largest task has at most this many views per step of the window (:class:`ViewBases`)."""

AUX = "interaction_loss."
"""The name prefix of the learned loss's parameters among a slot's phi^i."""


class BatchedMetaISAR(MetaRun, BatchedTrainer):
    """Meta-training with the ISAR base on the batched engine, per-task parameters (see
    the module docstring). Args as :class:`~geonav.policy.meta.MetaTrainer` with
    ``algo = 'isar'`` (``base_cfg`` an :class:`~geonav.policy.meta_config.ISARConfig`:
    its ``lr`` and Adam settings are the in-task Adam's, ``max_grad_norm`` its clip)."""

    base_algo = "isar"
    many_episodes_per_task = True
    cfg: Any
    """An ISARConfig (ISAR base) or an A3CConfig (A3C base)."""

    def __init__(self, env_factory: Any, net_cfg: Any, base_cfg: Any,
                 meta_cfg: MetaConfig | None = None, **kwargs: Any) -> None:
        check_a3c_base(base_cfg, PPO_BASE_META)
        super().__init__(env_factory, net_cfg, base_cfg, meta_cfg, **kwargs)
        # the trainable CNN: phi^i run-stacked in the model's layout, autograd gradients
        self.transposed_slots = self.frozen is not None

    def schedule(self) -> tuple[int, int]:
        """(steps per segment N, segments per window K)."""
        return self.cfg.n_steps, self.cfg.k_segments

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d["gradient_path"] = {**gradient_path(self.cfg), "path": "batched, per-task "
                              "parameters stacked (B, ...), inner updates as per-slot "
                              "rank-one factors on top"}
        return d

    def _setup(self) -> None:
        super()._setup()
        self.gram = gram_matrix(self.table)

    def record(self, f: dict[str, Any], stats: dict[str, float]) -> dict[str, Any]:
        rec = super().record(f, stats)
        if self.base_algo == "isar":  # the reference's ISAR columns (A3C has none)
            rec.update({"inner_updates": f["inner_updates"],
                        "adaptive_updates": f["adaptive_updates"], "kl_weight": 0.0})
        return rec

    def view_bases(self, phi: dict[str, torch.Tensor], rows: np.ndarray) -> ViewBases:
        """The window's view embeddings W x + b under the ``rows`` slots' phi^s (no graph)."""
        assert self.table is not None
        return ViewBases(phi, self.table, self.venv, self.schedule(), rows,
                         PRE_TABLE_VIEWS_PER_STEP)

    def segment(self, phi: dict[str, torch.Tensor], adapted: Adapted, state: State,
                alive: np.ndarray, views: ViewBases | None, rec: Recorder | None,
                rows: np.ndarray) -> tuple[LossTerms, State, list[dict[str, Any]]]:
        """Up to N lock-step steps with the graph under theta_s = phi^s + factors, the
        linear maps recorded in ``rec``: (the live slots' summed segment loss, the state,
        the finished episodes). The network runs on the window's slots ``rows`` (the
        slots live at its start, ascending; ``phi``, ``adapted`` and ``state`` hold their
        rows only); ``alive`` (B,) is updated in place. ``views`` None: the trainable CNN
        (every slot's rows, run-stacked phi; each slot's views encoded with its adapted
        weights, its target once per segment, recorded for the inner step)."""
        lc, e, dev = self.cfg.loss, self.net_cfg.embed_dim, self.device
        logits, values, actions, masks, rewards, ends, end_values = [], [], [], [], [], [], []
        finals: list[dict[str, Any]] = []
        table = self.table
        every = len(rows) == self.batch
        rows_t = None if every else torch.from_numpy(rows).to(dev)

        # with the Gram matrix the view embeddings' factors look their inputs up by row
        # index and their bases come from ViewBases: the feature rows themselves are not
        # read, so a zero placeholder of their shape saves two gathers per step
        blank = table.new_zeros(len(rows), table.shape[1]) \
            if table is not None and self.gram is not None else None
        cnn_tgt = None if views is not None else \
            self.slot_views(phi, adapted, self.slot_indices()[1], rec)

        def step(st: State, r: Recorder | None, leaf: bool) -> tuple[Any, Any, State]:
            vi, ti = self.slot_indices()
            if views is None:  # the trainable CNN, every slot
                return factored_step(phi, e, self.slot_views(phi, adapted, vi, r), cnn_tgt,
                                     st, adapted, r, None, vi, ti,
                                     self.slot_prev(phi, adapted, vi, r))
            assert table is not None
            if rows_t is not None:
                vi, ti = vi[rows_t], ti[rows_t]
            obs_f, tgt_f = (blank, blank) if blank is not None else (table[vi], table[ti])
            return factored_step(phi, e, obs_f, tgt_f, st, adapted, r, None, vi, ti,
                                 self.prev_features(vi), views.obs(vi, leaf), views.target)

        for _ in range(self.schedule()[0]):
            if not alive.any():
                break
            live = alive[rows]
            logit, value, state = step(state, rec, True)
            full = logit if every else logit.new_zeros(self.batch, logit.shape[1]) \
                .index_copy(0, rows_t, logit.detach())  # type: ignore[arg-type]
            act = sample_actions(full, self.rng, alive)  # draws for the live slots only
            res = self.venv.step(act.numpy(), autoreset=False)
            a = act.to(dev) if every else act[torch.from_numpy(rows)].to(dev)
            if lc.bootstrap_on_truncation:  # V(s) at a truncation under theta_s (no reset)
                end_values.append(np.zeros(len(rows)))
                if (res.truncated & alive).any():
                    with torch.no_grad():
                        v_end = step(state, None, False)[1]
                    end_values[-1] = np.where(res.truncated[rows], v_end.cpu().numpy(), 0.0)
            logits.append(logit)
            values.append(value)
            actions.append(a)
            masks.append(torch.from_numpy(live))
            rewards.append(np.where(live, res.rewards[rows], 0.0))
            ends.append(res.done[rows] & live)
            finals += [f for f in res.final if alive[f["slot"]]]
            alive &= ~res.done
        with torch.no_grad():  # V(s_next) under theta_s, without advancing the state
            v_next = step(state, None, False)[1]
        vs = torch.stack(values)
        (terms,) = segment_terms(torch.stack(logits), vs, torch.stack(actions),
                                 np.stack(rewards), np.stack(ends), v_next, lc,
                                 np.stack(end_values) if end_values else None,
                                 [torch.stack(masks).to(dev, vs.dtype)])
        return terms, state, finals

    def window_grads(self, loss: torch.Tensor, phi: dict[str, torch.Tensor], n_rows: int,
                     views: ViewBases | None, entries: list[Any], back: list[Any]
                     ) -> list[torch.Tensor]:
        """grad_phi^s of the window's loss for each of its ``n_rows`` slots, (n_rows, ...)
        per parameter (``phi``: every slot's, for the names and shapes).

        No parameter has a gradient edge in the graph: every use of a per-slot weight is a
        recorded map y = x W_s + b_s (its gradients sum_t x_t^T u_t and sum_t u_t from the
        output gradients u, :func:`~geonav.policy.batched.core.layer_grads`) or, in second
        order, a recorded backward product g_x = g_y W_s^T of an inner step
        (:func:`~geonav.policy.batched.core.back_grads`); the view embeddings' come from
        their leaves (constant inputs, evaluated once per window). One ``autograd.grad``
        w.r.t. those outputs, then one batched product per layer instead of an outer
        product per step. ``views`` None (the trainable CNN): ``phi`` is the run-stacked
        leaves of every slot, their gradients by autograd.
        """
        names = list(phi)
        if views is None:
            gs = torch.autograd.grad(loss, list(phi.values()), allow_unused=True)
            return [torch.zeros_like(x) if g is None else g.contiguous()
                    for x, g in zip(phi.values(), gs, strict=True)]
        entries = [en for en in entries if en[0] not in ("obs_embed", "target_embed")]
        ys = list({id(y): y for _, _, y, _ in entries}.values())
        gxs = [gx for _, gx, _ in back]
        leaves = views.leaves()
        gs = torch.autograd.grad(loss, ys + gxs + leaves, allow_unused=True)
        out = layer_grads(entries, {id(y): g for y, g in zip(ys, gs, strict=False)})
        for n, g in back_grads(back, list(gs[len(ys):len(ys) + len(gxs)])).items():
            out[n] = out[n] + g
        out.update(views.grads(gs[len(ys) + len(gxs):]))
        # contiguous: the fused Adam steps a parameter with its gradient's memory order
        return [out[n].contiguous() if n in out else phi[n].new_zeros(n_rows, *phi[n].shape[1:])
                for n in names]

    def update(self) -> tuple[list[dict[str, Any]], dict[str, float]]:
        """One meta-iteration: E episodes per slot on per-task parameters (one after
        another, phi^i and its Adam carried on), then the meta step."""
        if self._ran:  # the next tasks' episodes start here, so a checkpoint taken after
            self.next_round(self._ran)  # an update resumes with the same start draws
            self.t_episode[:] = time.perf_counter()
        jobs = self.jobs()
        n_jobs = int((jobs > 0).sum())
        phi, opt, task_grads = self.task_parameters()
        finals: list[dict[str, Any]] = []
        sums = np.zeros(3)  # policy, value, entropy
        live_segments = 0
        for e in range(int(jobs.max())):
            if e:  # the slots' next episodes on the same tasks
                self.venv.reset(starts=self._starts[:, e])
                self.t_episode[:] = time.perf_counter()
            fin, segs = self.episode(phi, opt, task_grads, jobs > e, sums)
            for f in fin:
                f["task_episode"] = e
            finals += fin
            live_segments += segs
        self.task_meta_step(task_grads, n_jobs, self.venv.slot_tasks[:n_jobs].tolist())
        for f in finals:
            f["t0"] = float(f.get("t0", self.t_episode[f["slot"]]))
            f["meta_update"] = self.meta_updates
        # records in batch order (a task's episodes in turn), as the reference's
        finals.sort(key=lambda f: (f["slot"], f["task_episode"]))
        self._ran = n_jobs
        # per live slot and segment (entropy: per step), as the reference's episode means
        segs = max(live_segments, 1)
        return finals, {"policy_loss": sums[0] / segs, "value_loss": sums[1] / segs,
                        "entropy": sums[2] / max(sum(f["length"] for f in finals), 1)}

    def episode(self, phi: dict[str, torch.Tensor], opt: SlotAdam,
                task_grads: list[torch.Tensor], alive: np.ndarray, sums: np.ndarray
                ) -> tuple[list[dict[str, Any]], int]:
        """One episode in every slot where ``alive`` (B,), from h = 0 on the slots' phi^i:
        windows of up to K segments, each followed by the live slots' Adam step; the
        window gradients are added to ``task_grads``, the loss figures to ``sums``.
        Returns the finished episodes and the live slot-segments."""
        cfg, dev, b = self.cfg, self.device, self.batch
        psi = self.params()
        k = self.schedule()[1]
        second_order = bool(getattr(cfg, "second_order", False)) and k > 1
        flush = bool(getattr(cfg, "flush_partial_window", True))
        dtype = values_dtype(self)
        alive = alive.copy()
        z = torch.zeros(b, self.net_cfg.lstm_size, dtype=dtype, device=dev)
        state: State = (z, z.clone(), torch.zeros(b, self.net_cfg.n_actions, dtype=dtype,
                                                  device=dev))
        inner = np.zeros(b, np.int64)
        adapt = np.zeros(b, np.int64)
        finals: list[dict[str, Any]] = []
        pl = vl = ent = 0.0
        live_segments = 0
        while alive.any():  # one window of up to K segments, then each slot's Adam step
            # the window runs on the slots live at its start only (a finished episode's
            # slot waits for the others without costing a row): their phi^i rows copied
            # (a few ms, against a window's steps) and their state's rows
            # rows; before the slots' first Adam step their weights are all psi's, shared
            rows = np.flatnonzero(alive)
            idx = torch.from_numpy(rows).to(dev)
            at_psi = all(float(opt.steps[s]) == 0.0 for s in rows)
            cnn = not self.transposed_slots
            if cnn:  # every slot's row (the CNN's per-slot weights span the B slots)
                phi_w = RunParams(phi)
            elif len(rows) == b and not at_psi:
                phi_w = phi
            elif at_psi:
                phi_w = AtPsi({n: x.detach() if x.dim() == 2 else
                               (phi[n] if len(rows) == b else
                                phi[n].detach()[idx].requires_grad_())
                               for n, x in psi.items()})
            else:
                phi_w = {n: x.detach()[idx].requires_grad_() for n, x in phi.items()}
            net_rows = np.arange(b) if cnn else rows
            state_w: State = state if len(net_rows) == b else \
                (state[0][idx], state[1][idx], state[2][idx])
            adapted: Adapted = {}
            window: list[torch.Tensor] = []
            entries: list[Any] = []
            back: list[Any] = []
            views = None if cnn else self.view_bases(phi_w, rows)
            adapt += alive
            dropped = np.zeros(b, bool)
            for j in range(k):
                live_segments += int(alive.sum())
                last = j == k - 1
                rec = Recorder(gram=self.gram)
                terms, state_w, fin = self.segment(phi_w, adapted, state_w, alive, views, rec,
                                                   net_rows)
                for f in fin:
                    s = f["slot"]
                    if not last and not flush:  # a partial window at done: no update
                        dropped[s] = True
                        adapt[s] -= 1
                    f["inner_updates"] = int(inner[s])
                    f["adaptive_updates"] = int(adapt[s])
                finals += fin
                window.append(terms.total)
                pl, vl = pl + float(terms.policy.detach()), vl + float(terms.value.detach())
                ent += float(terms.entropy.detach())
                entries += rec.entries
                if not alive.any():
                    break
                if not last:
                    live = torch.from_numpy(alive[net_rows]).to(dev, dtype)
                    adapted = rec.inner_factors(terms.total, adapted, cfg.alpha,
                                                create_graph=second_order, weights=live)
                    inner += alive
                    back += rec.back
            grads = self.window_grads(torch.stack(window).sum(), phi, len(net_rows), views,
                                      entries, back)
            if len(net_rows) > len(rows):  # the CNN's rows of slots whose episode ended
                grads = [g[idx].contiguous() for g in grads]
            if len(net_rows) == b:
                state = detach_state(state_w)
            else:
                h, c, p = (x.detach().index_copy(0, idx, y.detach())
                           for x, y in zip(state, state_w, strict=True))
                state = (h, c, p)
            if dropped.any():  # flush_partial_window = false: those slots' windows go
                keep = ~dropped[rows]  # unused, as the reference worker empties its window
                grads = [g[torch.from_numpy(keep).to(dev)] for g in grads]
                rows = rows[keep]
            if len(rows):
                self.step_slots(grads, rows)  # g_i += grads (unclipped); clip; Adam
        for f in finals:
            f["t0"] = float(self.t_episode[f["slot"]])
        sums += [pl, vl, ent]
        return finals, live_segments


class BatchedMetaA3C(BatchedMetaISAR):
    """Meta-training with the A3C base on the batched engine: :class:`BatchedMetaISAR`
    with windows of one ``t_max``-step rollout and no inner step (one per-task Adam step
    per rollout; g_i the sum of the rollout gradients). Args as
    :class:`~geonav.policy.meta.MetaTrainer` with ``algo = 'a3c'``."""

    base_algo = "a3c"

    def schedule(self) -> tuple[int, int]:
        return self.cfg.t_max, 1



BATCHED_META: dict[str, type] = {"savn": BatchedMetaSAVN, "isar": BatchedMetaISAR,
                                 "a3c": BatchedMetaA3C}
"""The batched meta-trainer of each base algorithm."""


__all__ = ["BatchedMetaSAVN", "BatchedMetaISAR", "BatchedMetaA3C", "BATCHED_META",
           "MetaRun", "clip_per_slot"]
