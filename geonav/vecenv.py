"""LatticeVecEnv: B independent GeoNavEnv episodes stepped together by index arithmetic.

The batched training engine (:mod:`geonav.policy.batched`) steps many episodes in
lock-step. Every observation of a lattice task is one of a few views (cells x
altitudes), so this environment renders each view once into a table and a step is a
gather: the current view of slot b is ``view_table[view_index[b]]`` and its target
``view_table[target_index[b]]``. With a frozen encoder the learner keeps the features of
the table instead of its pixels (:meth:`LatticeVecEnv.feature_table`).

Semantics are exactly :class:`geonav.env.GeoNavEnv`'s (which stays the Gymnasium face
and the reference; ``tests/test_vecenv.py`` compares trajectories): the task of a
new episode is drawn uniformly ("random") or in order ("cycle"), the start uniformly
among the free cells that reach the target within ``max_steps``; a move into an
obstacle or out of the region leaves the drone in place and counts as a collision;
+``success_reward`` and terminated on entering the target, else ``step_reward`` (plus
``collision_reward`` when refused); truncated after ``max_steps`` steps.

Each slot resets on its own, in the same step (auto-reset): :meth:`step` returns the
rewards and end flags of the step just taken, the finished episodes' summaries in
:attr:`StepResult.final`, and the slots' views after it (a new episode's start view
where a slot ended). Random draws come from one ``numpy`` generator per environment
(``reset(seed=...)``), so a run is reproducible, but the draws are not the same as B
separate GeoNavEnv instances' (the trajectories are equal for the same starts and
actions).

Imagery randomisation (:mod:`geonav.augment`): built on an env wrapped in
:class:`geonav.wrappers.ImageryRandomisation` (or given ``augment=``), the table holds
V = ``n_variants`` copies of every view, row ``k * n_cells + v`` being view v under
variant k, and each new episode of a slot draws its variant uniformly (after its task
and start, from the same generator). The view indices the environment hands out
(:attr:`view_index`, :attr:`target_index`, :attr:`StepResult.final_view`) are rows of
that table, so a learner that gathers rows by index trains on the variants unchanged,
and a table built from another altitude of the same augmented factory (the curriculum's
previous-altitude view and its teacher) has the same rows. The current and the target
view of an episode share its variant: the paper's agent compares what it sees with a
target taken from the same imagery, and a season or exposure change affects the whole
scene at once, so the variation that transfer meets (urban -> wild, another flight) is
between episodes, not inside one; independent variants would add a harder
cross-appearance matching problem that no evaluation poses. Evaluation builds its own
environment on the bare env and sees clean imagery.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from geonav.augment import AugmentConfig, augment_images
from geonav.env import GeoNavEnv
from geonav.errors import ConfigError, TaskError
from geonav.tasks import ACTION_MOVES

_MOVES = np.asarray(ACTION_MOVES, np.int64)  # (A, 2): dx, dy


@dataclass
class StepResult:
    """What :meth:`LatticeVecEnv.step` returns (arrays of shape (B,))."""

    rewards: np.ndarray
    """float64 rewards of the step."""
    terminated: np.ndarray
    """bool: the slot entered its target."""
    truncated: np.ndarray
    """bool: the slot hit its step cap without reaching the target."""
    collided: np.ndarray
    """bool: the move was refused (obstacle or region edge)."""
    final_view: np.ndarray
    """int64 view index (table row, with the episode's variant) where the step left each
    slot (before any auto-reset)."""
    final: list[dict[str, Any]]
    """One summary per finished episode: slot, task, task_index, length, success,
    shortest_path, return, collisions."""

    @property
    def done(self) -> np.ndarray:
        return self.terminated | self.truncated


def physical_memory_bytes() -> int | None:
    """This machine's physical memory in bytes (None where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def check_table_memory(need_bytes: int, what: str) -> None:
    """TaskError before a view table larger than most of this machine's memory is allocated."""
    total = physical_memory_bytes()
    if total is not None and need_bytes > 0.8 * total:
        raise TaskError(f"the views of {what} need {need_bytes / (1 << 30):.1f} GiB, more than "
                        f"this machine's {total / (1 << 30):.1f} GiB allow; use a larger "
                        "lattice step (geonav tasks make --step), fewer tasks or a smaller "
                        "--obs-size")


class LatticeVecEnv:
    """B lock-stepped episodes over the tasks of a :class:`GeoNavEnv` (see module docstring).

    Args:
        env: the reference environment; its scene, tasks, camera, rewards, caps and task
            sampling are used (``env.unwrapped``).
        n_slots: B, the number of parallel episodes.
        slot_tasks: per slot, a fixed task index for every episode of that slot (None or
            -1: drawn by the env's ``task_sampling``). Meta-training pins tasks to slots.
        augment: imagery randomisation (an :class:`~geonav.augment.AugmentConfig`); None
            takes the one of an :class:`~geonav.wrappers.ImageryRandomisation` around
            ``env``, if any.
    """

    def __init__(self, env: Any, n_slots: int, *, slot_tasks: Any = None,
                 augment: AugmentConfig | None = None) -> None:
        u: GeoNavEnv = env.unwrapped
        if augment is None:
            augment = find_augment(env)
        self.augment = augment
        self.n_variants = 1 if augment is None else augment.n_variants
        """V: copies of every view in the table (1 without randomisation)."""
        if n_slots < 1:
            raise ConfigError(f"n_slots must be >= 1, got {n_slots}")
        self.env = u
        self.n_slots = int(n_slots)
        self.n_tasks = len(u.task_maps)
        shapes = [tm.lattice.shape for tm in u.task_maps]
        sizes = [nx * ny for nx, ny in shapes]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        """View index of cell (ix, iy) of task i: offsets[i] + ix * ny_i + iy."""
        self.n_cells = int(self.offsets[-1])
        """Distinct (task, cell) views."""
        self.n_views = self.n_variants * self.n_cells
        """Rows of the view table: every (task, cell) view under every variant."""
        self.nx = np.asarray([s[0] for s in shapes], np.int64)
        self.ny = np.asarray([s[1] for s in shapes], np.int64)
        self.max_steps = np.asarray([u.max_steps_of(i) for i in range(self.n_tasks)], np.int64)
        self.target = np.asarray([tm.task.target_cell for tm in u.task_maps], np.int64)
        self.target_view = np.asarray([self.view_of(i, tuple(self.target[i]))
                                       for i in range(self.n_tasks)], np.int64)
        self._blocked = [tm.blocked.astype(bool) for tm in u.task_maps]
        self._walls: np.ndarray | None = None  # built by feasible_moves
        self._dist = [tm.dist_to_target.astype(np.int64) for tm in u.task_maps]
        self._starts = [np.asarray(u.start_cells(i), np.int64) for i in range(self.n_tasks)]
        self.view_task = np.tile(np.repeat(np.arange(self.n_tasks), sizes),
                                 self.n_variants).astype(np.int64)
        """Task of every view index (table row)."""
        self.slot_tasks = np.full(self.n_slots, -1, np.int64) if slot_tasks is None else \
            np.asarray(slot_tasks, np.int64).reshape(self.n_slots)
        if (self.slot_tasks >= self.n_tasks).any():
            raise TaskError(f"slot task index out of range 0..{self.n_tasks - 1}")
        self.np_random = np.random.default_rng()
        self._cycle = -1
        b = self.n_slots
        self.task = np.zeros(b, np.int64)
        self.cell = np.zeros((b, 2), np.int64)
        self.variant = np.zeros(b, np.int64)
        """Imagery variant of every slot's episode (0 without randomisation)."""
        self.start = np.zeros((b, 2), np.int64)
        self.steps = np.zeros(b, np.int64)
        self.ep_return = np.zeros(b, np.float64)
        self.collisions = np.zeros(b, np.int64)
        self._images: np.ndarray | None = None
        self._clean: np.ndarray | None = None

    # -- tables -----------------------------------------------------------------------------
    def view_of(self, task_index: int, cell: tuple[int, int], variant: int = 0) -> int:
        """Table row of a cell of a task under an imagery variant."""
        return int(variant * self.n_cells + self.offsets[task_index]
                   + cell[0] * self.ny[task_index] + cell[1])

    def view_cells(self) -> list[tuple[int, tuple[int, int]]]:
        """(task index, cell) of every view of one variant (rows 0..n_cells-1), in order."""
        return [(i, (x, y)) for i in range(self.n_tasks)
                for x in range(int(self.nx[i])) for y in range(int(self.ny[i]))]

    def _clean_table(self) -> np.ndarray:
        """(n_cells, N, N, 3) uint8: the rendered views of the clean imagery (built once)."""
        if self._clean is None:
            n = self.env.camera.size_px
            check_table_memory(self.n_cells * max(1, self.n_variants) * n * n * 3,
                               f"{self.n_cells:,} cells of {n} px views"
                               + (f" in {self.n_variants} imagery variants"
                                  if self.n_variants > 1 else ""))
            out = np.empty((self.n_cells, n, n, 3), np.uint8)
            for v, (ti, cell) in enumerate(self.view_cells()):
                out[v] = self.env.observation_at(ti, cell)
            self._clean = out
        return self._clean

    def image_table(self) -> np.ndarray:
        """(n_views, N, N, 3) uint8: the rendered view of every (task, cell) under every
        imagery variant, variant-major (built once)."""
        if self._images is None:
            clean, c = self._clean_table(), self.n_cells
            if self.augment is None:
                self._images = clean
            else:
                out = np.empty((self.n_views, *clean.shape[1:]), np.uint8)
                for k in range(self.n_variants):
                    out[k * c:(k + 1) * c] = augment_images(clean, self.augment.params(k))
                self._images = out
                self._clean = None  # the variant copies replace it
        return self._images

    def feature_table(self, frozen: Any, chunk: int = 256) -> Any:
        """(n_views, F) features of every view through a frozen encoder (a torch tensor).

        With imagery variants and no image table built yet, the variants are rendered and
        encoded chunk by chunk, so only the clean images and the features stay in memory
        (not V copies of the pixels)."""
        import torch

        out: Any = None

        def put(row: int, images: np.ndarray) -> None:
            nonlocal out
            f = frozen.encode(torch.from_numpy(images))
            if out is None:  # filled in place: no list of parts and no torch.cat copy
                out = torch.empty((self.n_views, *f.shape[1:]), dtype=f.dtype)
            out[row:row + len(f)] = f

        if self._images is not None or self.augment is None:
            images = self.image_table()
            for i in range(0, self.n_views, chunk):
                put(i, images[i:i + chunk])
        else:
            clean, c = self._clean_table(), self.n_cells
            for k in range(self.n_variants):
                p = self.augment.params(k)
                for i in range(0, c, chunk):
                    put(k * c + i, augment_images(clean[i:i + chunk], p))
        if getattr(frozen, "pairwise", False):  # 'corr': each row against its own target
            out = frozen.combine(out, out[torch.from_numpy(self.target_rows)])
        return out

    @property
    def target_rows(self) -> np.ndarray:
        """(n_views,) the table row of every row's target view (same task and variant)."""
        rows = np.arange(self.n_views, dtype=np.int64)
        return (rows // self.n_cells) * self.n_cells + self.target_view[self.view_task]

    @property
    def view_index(self) -> np.ndarray:
        """(B,) view index (table row) of every slot's current cell and variant."""
        return self.variant * self.n_cells + self.offsets[self.task] \
            + self.cell[:, 0] * self.ny[self.task] + self.cell[:, 1]

    @property
    def target_index(self) -> np.ndarray:
        """(B,) view index (table row) of every slot's target cell and variant."""
        return self.variant * self.n_cells + self.target_view[self.task]

    # -- episodes ---------------------------------------------------------------------------
    def seed(self, seed: int | None) -> None:
        self.np_random = np.random.default_rng(seed)

    def reset(self, *, seed: int | None = None, tasks: Any = None, starts: Any = None,
              variants: Any = None) -> None:
        """Start a new episode in every slot (``tasks``/``starts``/``variants`` force them,
        per slot)."""
        if seed is not None:
            self.seed(seed)
        self.reset_slots(np.arange(self.n_slots), tasks, starts, variants)

    def _draw_task(self, slot: int) -> int:
        if self.slot_tasks[slot] >= 0:
            return int(self.slot_tasks[slot])
        if self.env.task_sampling == "cycle":
            self._cycle = (self._cycle + 1) % self.n_tasks
            return self._cycle
        return int(self.np_random.integers(self.n_tasks))

    def draw_start(self, task: int) -> np.ndarray:
        """A start cell of task ``task`` (GeoNavEnv's start distribution), one draw."""
        cands = self._starts[task]
        return cands[int(self.np_random.integers(len(cands)))]

    def reset_slots(self, slots: Any, tasks: Any = None, starts: Any = None,
                    variants: Any = None) -> None:
        """New episodes in ``slots`` (in order): task drawn (or forced), then the start,
        then (with V > 1 variants) the imagery variant."""
        for j, s in enumerate(np.asarray(slots, np.int64).tolist()):
            ti = self._draw_task(s) if tasks is None else int(tasks[j])
            if not 0 <= ti < self.n_tasks:
                raise TaskError(f"task index {ti} out of range 0..{self.n_tasks - 1}")
            if starts is None:
                start = self.draw_start(ti)
            else:
                start = np.asarray(starts[j], np.int64)
                if not (0 <= start[0] < self.nx[ti] and 0 <= start[1] < self.ny[ti]) \
                        or self._blocked[ti][tuple(start)]:
                    raise TaskError(f"start cell {tuple(start)} is outside the lattice or "
                                    "blocked")
                if self._dist[ti][tuple(start)] < 0:
                    raise TaskError(f"the target is unreachable from start cell "
                                    f"{tuple(start)}")
            if variants is not None:
                k = int(variants[j])
                if not 0 <= k < self.n_variants:
                    raise TaskError(f"variant {k} out of range 0..{self.n_variants - 1}")
            else:
                # no draw without randomisation: the task/start stream stays as before
                k = int(self.np_random.integers(self.n_variants)) if self.n_variants > 1 else 0
            self.variant[s] = k
            self.task[s] = ti
            self.cell[s] = start
            self.start[s] = start
            self.steps[s] = 0
            self.ep_return[s] = 0.0
            self.collisions[s] = 0

    def feasible_moves(self) -> np.ndarray:
        """(B, A) bool: whether each action moves each slot (stays on its task's lattice and
        does not enter a blocked cell); the others are refused as collisions."""
        if self._walls is None:  # (tasks, nx + 2, ny + 2): blocked, or off the lattice
            walls = np.ones((self.n_tasks, int(self.nx.max()) + 2, int(self.ny.max()) + 2),
                            bool)
            for i, b in enumerate(self._blocked):
                walls[i, 1:b.shape[0] + 1, 1:b.shape[1] + 1] = b
            self._walls = walls
        nxt = self.cell[:, None, :] + _MOVES[None] + 1              # (B, A, 2), padded
        return ~self._walls[self.task[:, None], nxt[..., 0], nxt[..., 1]]

    def step(self, actions: Any, *, autoreset: bool = True) -> StepResult:
        """Move every slot by its action (B,) and auto-reset the slots that finished."""
        a = np.asarray(actions, np.int64).reshape(self.n_slots)
        if ((a < 0) | (a >= len(_MOVES))).any():
            raise ValueError(f"actions must lie in Discrete({len(_MOVES)}), got {a}")
        u = self.env
        nxt = self.cell + _MOVES[a]
        ti = self.task
        inside = (nxt[:, 0] >= 0) & (nxt[:, 0] < self.nx[ti]) & (nxt[:, 1] >= 0) \
            & (nxt[:, 1] < self.ny[ti])
        collided = ~inside
        for s in np.nonzero(inside)[0].tolist():
            collided[s] = bool(self._blocked[ti[s]][nxt[s, 0], nxt[s, 1]])
        self.cell = np.where(collided[:, None], self.cell, nxt)
        self.steps += 1
        terminated = (self.cell == self.target[ti]).all(axis=1)
        rewards = np.where(terminated, u.success_reward,
                           u.step_reward + np.where(collided, u.collision_reward, 0.0))
        truncated = ~terminated & (self.steps >= self.max_steps[ti])
        self.ep_return += rewards
        self.collisions += collided
        final_view = self.view_index
        done = terminated | truncated
        final = []
        for s in np.nonzero(done)[0].tolist():
            final.append({"slot": s, "task": u.task_maps[ti[s]].task.name,
                          "task_index": int(ti[s]), "length": int(self.steps[s]),
                          "success": bool(terminated[s]),
                          "shortest_path": int(self._dist[ti[s]][tuple(self.start[s])]),
                          "return": float(self.ep_return[s]),
                          "collisions": int(self.collisions[s])})
        if autoreset and done.any():
            self.reset_slots(np.nonzero(done)[0])
        return StepResult(rewards.astype(np.float64), terminated, truncated, collided,
                          final_view, final)

    def info(self, slot: int, collided: bool = False) -> dict[str, Any]:
        """GeoNavEnv's ``info`` dict for one slot's current state."""
        tm = self.env.task_maps[int(self.task[slot])]
        cell = (int(self.cell[slot, 0]), int(self.cell[slot, 1]))
        p = tm.lattice.center(cell)
        return {"position_m": (p.x_m, p.y_m), "cell": cell, "target_cell": tm.task.target_cell,
                "distance_m": int(tm.dist_to_target[cell]) * tm.task.step_m,
                "shortest_path": int(tm.dist_to_target[tuple(self.start[slot])]),
                "collided": bool(collided), "success": cell == tm.task.target_cell,
                "is_success": cell == tm.task.target_cell,
                "task": tm.task.name, "task_index": int(self.task[slot]),
                "task_key": self.env.task_key(int(self.task[slot])),
                "alt_m": tm.task.alt_m, "steps": int(self.steps[slot]),
                **({} if self.augment is None
                   else {"augment_variant": int(self.variant[slot])})}

    def table_bytes(self, frozen_dim: int | None = None) -> int:
        """Bytes of the observation table (all variants): images, or float32 features of
        width F."""
        if frozen_dim is not None:
            return self.n_views * frozen_dim * 4
        n = self.env.camera.size_px
        return self.n_views * n * n * 3


def find_augment(env: Any) -> AugmentConfig | None:
    """The :class:`~geonav.augment.AugmentConfig` of the first
    :class:`~geonav.wrappers.ImageryRandomisation` around ``env`` (None if there is none)."""
    import gymnasium as gym

    from geonav.wrappers import ImageryRandomisation

    e = env
    while isinstance(e, gym.Wrapper):
        if isinstance(e, ImageryRandomisation):
            return e.augment
        e = e.env
    return None


__all__ = ["LatticeVecEnv", "StepResult", "find_augment"]
