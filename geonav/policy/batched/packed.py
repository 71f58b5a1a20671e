"""Packed runs: several independent batched runs (A3C, PPO, ISAR, SAVN) in one process batch.

A packed group is R *member* trainers, each an ordinary single-run trainer of the same
algorithm (:class:`~geonav.policy.batched.trainer.BatchedA3CTrainer`,
:class:`~geonav.policy.batched.ppo.BatchedPPOTrainer`,
:class:`~geonav.policy.batched.isar.BatchedISARTrainer`,
:class:`~geonav.policy.batched.savn.BatchedSAVNTrainer`) with its own seed, parameters,
Adam, random streams, ``batch`` slots (the per-run batch, default 16), run folder,
callbacks, checkpoints and resume, and one *driver*: an instance of the same algorithm's
class whose slots are the members' slots side by side (R x B) and whose update is that
class's own ``update`` method, unchanged. The driver differs from a single run in four
hooks only:

* ``params()``: the members' parameters stacked along a leading run dimension
  (``torch.stack``, so gradients flow back to each member's own leaves); every linear
  map of :mod:`geonav.policy.batched.core` applies run r's weights to run r's rows
  (:func:`~geonav.policy.batched.core.affine`, one batched matrix product per layer);
* ``apply_gradients()``: each member clips its own gradient norm and steps its own Adam
  (exactly the single run's step);
* the random streams: actions and PPO's minibatch order are drawn from each member's own
  generator, the environment slots are the members' own vector envs;
  SAVN's learned loss is each member's own (its parameters gathered per slot);
* the view tables: each run's image part of every view (``view_rows``, ``acting_tables``).
  With the trainable CNN, each run encodes the update's distinct views (the union over
  the runs' slots) with its own weights, in one grouped call (``features``); acting uses
  each member's own tables; ISAR's and SAVN's per-slot adapted CNN starts from its run's
  weights (:func:`~geonav.policy.batched.core.encoder_weights`).

Losses are sums of per-slot terms divided by the per-run batch (PPO: per-run means), so
each run's gradient is the one it would have alone: two runs packed give the same
parameters as the same runs made alone (``tests/test_batched_packed.py``, float64).

Why a per-run batch rather than one run of R x B slots: a run's updates per episode
stay those of a B-worker A3C (B = 16 is the order of the paper's and SAVN's worker
counts), so episodes-to-convergence stay comparable with the paper's, while the process
batch is R x B (docs/guide.md, the batched engine).

SAVN's episode-synchronous rounds last as long as the longest episode of the process
batch, longer than a run's own round would; its slots draw actions only while in their
episode (``sample_actions(live=...)``), so a member waiting for the others draws nothing
and its streams stay those of the run alone.

Not packed: meta-training, the curriculum teacher and the previous-altitude view input.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from geonav.errors import ConfigError
from geonav.policy.a3c import TrainResult
from geonav.policy.batched.core import ActingTables, Params, RunParams, encode_slots
from geonav.policy.batched.isar import BatchedISARTrainer
from geonav.policy.batched.ppo import BatchedPPOTrainer
from geonav.policy.batched.savn import BatchedSAVNTrainer
from geonav.policy.batched.trainer import BatchedA3CTrainer, BatchedTrainer
from geonav.policy.config import to_dict
from geonav.vecenv import StepResult

log = logging.getLogger(__name__)


class StackedVecEnv:
    """R vector envs of B slots each seen as one of R x B slots (slots in run order)."""

    def __init__(self, venvs: Sequence[Any]) -> None:
        self.venvs = list(venvs)
        self.per_run = self.venvs[0].n_slots
        self.n_slots = self.per_run * len(self.venvs)
        self.n_views = self.venvs[0].n_views
        self.env_steps = 0
        """Slot steps taken so far (benchmarks)."""

    @property
    def view_index(self) -> np.ndarray:
        return np.concatenate([v.view_index for v in self.venvs])

    @property
    def target_index(self) -> np.ndarray:
        return np.concatenate([v.target_index for v in self.venvs])

    def reset(self) -> None:
        """A new episode in every slot, each member's env with its own draws."""
        for v in self.venvs:
            v.reset()

    def step(self, actions: Any, *, autoreset: bool = True) -> StepResult:
        a = np.asarray(actions).reshape(len(self.venvs), self.per_run)
        parts = [v.step(a[i], autoreset=autoreset) for i, v in enumerate(self.venvs)]
        self.env_steps += self.n_slots
        final = []
        for i, res in enumerate(parts):
            for f in res.final:
                final.append({**f, "slot": f["slot"] + i * self.per_run})
        return StepResult(*(np.concatenate([getattr(r, k) for r in parts]) for k in
                            ("rewards", "terminated", "truncated", "collided", "final_view")),
                          final)


class StackedRng:
    """The members' numpy generators as one: ``random(R * B)`` draws B from each in turn."""

    def __init__(self, rngs: Sequence[np.random.Generator]) -> None:
        self.rngs = list(rngs)

    def random(self, n: int) -> np.ndarray:
        k = n // len(self.rngs)
        return np.concatenate([g.random(k) for g in self.rngs])

    def random_live(self, live: np.ndarray) -> np.ndarray:
        """One draw per live row (R * B,), each run's from its own generator."""
        per = np.asarray(live).reshape(len(self.rngs), -1).sum(1)
        return np.concatenate([g.random(int(n)) for g, n in zip(self.rngs, per, strict=True)])


class _AllViewTables(ActingTables):
    """Acting tables of packed runs: every run's image part of every view, computed at
    once (rows run-major), looked up at ``view + run * n_views``."""

    def __init__(self, params: Params, embed_dim: int, n_views: int, runs: int,
                 per_run: int, features: Any) -> None:
        super().__init__(params, embed_dim, n_views * runs, lambda rows: features(rows % n_views))
        self.offset = (torch.arange(runs * per_run, device=self._obs.device) // per_run) \
            * n_views

    def pre(self, view_idx: torch.Tensor, target_idx: torch.Tensor) -> torch.Tensor:
        if not bool(self._filled.all()):
            self._fill(torch.arange(self._filled.shape[0], device=self._obs.device))
        return self._obs[view_idx + self.offset] + self._tgt[target_idx + self.offset]


class _RunTables(ActingTables):
    """Acting tables of packed runs with the trainable CNN: each member's own lazily
    filled tables (its weights, its met views), its slots' rows looked up there."""

    def __init__(self, members: Sequence[BatchedTrainer], per_run: int) -> None:
        self.tables = [m.acting_tables() for m in members]
        self.per_run = per_run

    def pre(self, view_idx: torch.Tensor, target_idx: torch.Tensor) -> torch.Tensor:
        b = self.per_run
        return torch.cat([t.pre(view_idx[i * b:(i + 1) * b], target_idx[i * b:(i + 1) * b])
                          for i, t in enumerate(self.tables)])


class PackedTrainer(BatchedTrainer):
    """The driver of a packed group (see the module docstring); build it with
    :meth:`from_members`, never with the trainer constructor."""

    members: list[BatchedTrainer]
    packs_aux = False
    """True where the driver runs each member's modules beside the policy (SAVN's loss)."""

    @classmethod
    def from_members(cls, members: Sequence[BatchedTrainer]) -> PackedTrainer:
        check_packable(members)
        self = cls.__new__(cls)
        m0 = members[0]
        self.members = list(members)
        self.cfg, self.net_cfg, self.device = m0.cfg, m0.net_cfg, m0.device
        self.run_batch = m0.batch
        self.batch = m0.batch * len(members)
        self.model, self.frozen, self.env = m0.model, m0.frozen, m0.env
        self.aux = {}
        self.on_gradients = None
        self.teacher_spec = None
        self.prev_view_spec = None
        self.episodes_done = 0
        return self

    # -- the four hooks -------------------------------------------------------------------
    def params(self) -> Params:
        per = [dict(m.model.named_parameters()) for m in self.members]
        return RunParams({n: torch.stack([p[n] for p in per]) for n in per[0]})

    def step_optimizer(self, loss: torch.Tensor) -> None:
        for m in self.members:
            m.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.apply_gradients()

    def apply_gradients(self) -> None:
        for m in self.members:
            if not getattr(m, "packed_done", False):
                m.apply_gradients()

    def run_rngs(self) -> list[np.random.Generator]:
        return [m.rng for m in self.members]

    def run_slices(self) -> list[slice]:
        b = self.run_batch
        return [slice(i * b, (i + 1) * b) for i in range(len(self.members))]

    def view_rows(self, view_idx: torch.Tensor, target_idx: torch.Tensor,
                  slots: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        c, r = self.venv.n_views, len(self.members)
        if slots is None:
            slots = torch.arange(view_idx.shape[1], device=view_idx.device)
        off = (slots // self.run_batch) * c
        if self.images is not None:  # trainable CNN: the distinct views, once per run
            uniq, inv = torch.unique(torch.cat([view_idx.flatten(), target_idx.flatten()]),
                                     return_inverse=True)
            n, off = view_idx.numel(), (slots // self.run_batch) * uniq.numel()
            return (uniq.repeat(r), inv[:n].view_as(view_idx) + off,
                    inv[n:].view_as(target_idx) + off)
        rows = torch.arange(c, device=view_idx.device).repeat(r)
        return rows, view_idx + off, target_idx + off

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        """(R * n, F) features of R equal groups of view rows, run r's with its weights
        (the trainable CNN: one grouped call; a frozen table: a lookup)."""
        if self.table is not None:
            return self.table[rows]
        assert self.images is not None and self.model.encoder is not None
        r = len(self.members)
        w = {n[len("encoder."):]: p for n, p in self.params().items()
             if n.startswith("encoder.")}
        imgs = self.images[rows].reshape(r, -1, *self.images.shape[1:])
        return encode_slots(self.model.encoder, w, imgs).reshape(rows.shape[0], -1)

    def acting_tables(self) -> ActingTables:
        if self.images is not None:
            return _RunTables(self.members, self.run_batch)
        return _AllViewTables(self.params(), self.net_cfg.embed_dim, self.venv.n_views,
                              len(self.members), self.run_batch, self.features)

    # -- state ----------------------------------------------------------------------------
    def _setup(self) -> None:
        for m in self.members:
            m._setup()
        ms = self.members
        self.venv = StackedVecEnv([m.venv for m in ms])  # type: ignore[assignment]
        self.rng = StackedRng([m.rng for m in ms])  # type: ignore[assignment]
        self.table, self.images, self.prev_table = ms[0].table, ms[0].images, None
        self.prev_images = None
        self.state = tuple(torch.cat([m.state[k] for m in ms]) for k in range(3))  # type: ignore
        self.fresh = torch.cat([m.fresh for m in ms])
        self.t_episode = np.concatenate([m.t_episode for m in ms])
        self.slot_episode = np.concatenate([m.slot_episode for m in ms])
        self.next_episode = max(m.next_episode for m in ms)

    # -- the loop -------------------------------------------------------------------------
    def train(self) -> list[TrainResult]:  # type: ignore[override]
        """Train every member to its budget (each its own run folder, checkpoints and
        records, as :meth:`BatchedTrainer.train`); returns the members' results."""
        begun = [m.begin_training() for m in self.members]
        threads = torch.get_num_threads()
        torch.set_num_threads(self.cfg.torch_threads)
        b = self.run_batch
        try:
            self._setup()
            for m, (cbs, result) in zip(self.members, begun, strict=True):
                m.packed_done = m.episodes_done >= m.cfg.episodes  # type: ignore[attr-defined]
                if m.packed_done:  # resumed at its budget: only its final files are left
                    m._final_rng = m.rng_snapshot()
                    m.finish_training(cbs, result)
            while not all(m.packed_done for m in self.members):  # type: ignore[attr-defined]
                training = [not m.packed_done for m in self.members]  # type: ignore
                finals, stats = self.update()
                for f in finals:
                    i = f["slot"] // b
                    m, (cbs, result) = self.members[i], begun[i]
                    if m.packed_done or m.episodes_done >= m.cfg.episodes:  # type: ignore
                        continue
                    f = {**f, "slot": f["slot"] % b}
                    rec = m.record(f, stats[i] if isinstance(stats, list) else stats)
                    if not m._on_record(rec, cbs, result, m.rng_snapshot) or \
                            m.episodes_done >= m.cfg.episodes:
                        m.packed_done = True  # type: ignore[attr-defined]
                        m._final_rng = m.rng_snapshot()
                        m.finish_training(cbs, result)
                for i, (m, (cbs, result)) in enumerate(zip(self.members, begun, strict=True)):
                    if training[i]:  # each member's own losses, once per update
                        m.report_update(stats[i] if isinstance(stats, list) else stats, cbs,
                                        result)
        finally:
            torch.set_num_threads(threads)
            for cbs, result in begun:
                for cb in cbs:
                    cb.on_train_end(result)
        return [result for _, result in begun]

    def record(self, f: dict[str, Any], stats: Any) -> dict[str, Any]:  # pragma: no cover
        raise NotImplementedError("a packed driver's episodes are recorded by its members")


class PackedA3C(BatchedA3CTrainer, PackedTrainer):
    """Packed batched A3C runs."""


class PackedPPO(BatchedPPOTrainer, PackedTrainer):
    """Packed PPO runs."""


class PackedISAR(BatchedISARTrainer, PackedTrainer):
    """Packed ISAR runs (first or second order)."""


class PackedSAVN(BatchedSAVNTrainer, PackedTrainer):
    """Packed SAVN runs: each member's learned loss on its slots."""

    packs_aux = True

    def aux_module(self) -> torch.nn.Module:
        return self.members[0].aux["interaction_loss"]

    def loss_params(self) -> tuple[dict[str, torch.Tensor], int | None]:
        per = [dict(m.aux["interaction_loss"].named_parameters()) for m in self.members]
        run = torch.arange(self.batch, device=self.device) // self.run_batch
        return {n: torch.stack([p[n] for p in per])[run] for n in per[0]}, 0


PACKED: dict[type, type[PackedTrainer]] = {BatchedA3CTrainer: PackedA3C,
                                           BatchedPPOTrainer: PackedPPO,
                                           BatchedISARTrainer: PackedISAR,
                                           BatchedSAVNTrainer: PackedSAVN}
"""Single-run trainer class -> its packed driver."""


def packing_refusal(members: Sequence[Any]) -> str | None:
    """Why these trainers cannot be packed, or None (for a logged fallback)."""
    if not members:
        return "no members"
    m0 = members[0]
    if type(m0) not in PACKED or any(type(m) is not type(m0) for m in members):
        return (f"packing is implemented for {sorted(c.algorithm for c in PACKED)} on the "
                f"batched engine, all members of one algorithm; got "
                f"{sorted({type(m).__name__ for m in members})}")
    if getattr(m0, "teacher_spec", None) is not None or m0.prev_view_spec is not None:
        return "packed runs do not take the curriculum teacher or the previous-view input"
    if any(getattr(m.env_factory, "augment", None) is not None for m in members):
        return "imagery randomisation (augment) gives each run its own view tables"
    if m0.aux and not PACKED[type(m0)].packs_aux:
        return f"{m0.algorithm} trains modules beside the policy ({sorted(m0.aux)})"
    ref = _shape(m0)
    for m in members[1:]:
        if _shape(m) != ref:
            return (f"members differ in network, batch, device or settings other than "
                    f"seed and budget: {ref} vs {_shape(m)}")
    return None


def _shape(m: Any) -> tuple[Any, ...]:
    cfg = {k: v for k, v in to_dict(m.cfg).items() if k not in ("seed", "episodes")}
    return (to_dict(m.net_cfg), m.batch, str(m.device), cfg,
            [t.name for t in m.env.unwrapped.tasks])


def check_packable(members: Sequence[Any]) -> None:
    reason = packing_refusal(members)
    if reason is not None:
        raise ConfigError(f"these runs cannot be packed: {reason}")


def pack(members: Sequence[BatchedTrainer]) -> PackedTrainer:
    """The driver of a packed group of member trainers (see the module docstring)."""
    check_packable(members)
    return PACKED[type(members[0])].from_members(members)


def train_packed(members: Sequence[BatchedTrainer]) -> list[TrainResult]:
    """Train member trainers packed in one batch; returns their results in order."""
    t0 = time.perf_counter()
    results = pack(members).train()
    log.info("packed %d %s runs in %.1f s", len(members), members[0].algorithm,
             time.perf_counter() - t0)
    return results


__all__ = ["PackedTrainer", "PackedA3C", "PackedPPO", "PackedISAR", "PackedSAVN", "pack",
           "train_packed",
           "packing_refusal", "check_packable"]
