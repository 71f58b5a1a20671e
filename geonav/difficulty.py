"""How hard a navigation task is by chance: exact random-walk success, shortest paths.

A learning result means something only beside what no learning already achieves
(ALGORITHMS.md (f)). For a bound task (:class:`geonav.lattice.TaskMap`) this module
computes, exactly and without sampling, by dynamic programming over the lattice:

* the success probability of a uniform random walk within ``max_steps`` from the
  env's start distribution (uniform over :meth:`TaskMap.start_cells`), with the env's
  move rule: a move into an obstacle or out of the region leaves the agent in place;
  reaching the target ends the episode;
* the same for any stationary action distribution ``q``, and the best such distribution
  on a simplex grid: the **view-blind** line, the success of a policy that knows the
  task's target but ignores the current view, i.e. a directional bias alone (a target in
  a region corner is reached by a fixed diagonal bias from every start, so its view-blind
  success is near 1; tasks that are to show navigation by the view need it low,
  ALGORITHMS.md (f));
* the mean BFS shortest path from the starts.

The recursion: with ``P_k(c)`` the probability of reaching the target within ``k``
steps from cell ``c``, ``P_0 = [c = target]`` and
``P_{k+1}(c) = [c = target] + [c != target] * sum_a q_a P_k(next_a(c))``.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from geonav.errors import TaskError
from geonav.lattice import ACTION_MOVES, TaskMap, bind


def _next_index(blocked: np.ndarray) -> np.ndarray:
    """(4, nx*ny) flat index of the cell each action leads to (self where refused)."""
    nx, ny = blocked.shape
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    own = (ix * ny + iy).ravel()
    out = np.empty((len(ACTION_MOVES), nx * ny), np.int64)
    for a, (dx, dy) in enumerate(ACTION_MOVES):
        u, v = ix + dx, iy + dy
        inside = (u >= 0) & (u < nx) & (v >= 0) & (v < ny)
        ok = inside.copy()
        ok[inside] = ~blocked[u[inside], v[inside]]
        nxt = np.where(ok, u * ny + v, ix * ny + iy).ravel()
        out[a] = np.where(ok.ravel(), nxt, own)
    return out


def success_within(blocked: np.ndarray, target: tuple[int, int], max_steps: int,
                   probs: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Probability that a stationary random policy reaches ``target`` within ``max_steps``
    steps from each cell.

    Args:
        blocked: (nx, ny) bool obstacle cells (``TaskMap.blocked``).
        target: the target cell.
        max_steps: the episode cap T_max.
        probs: action probabilities q, (4,) or a batch (Q, 4); default uniform.

    Returns:
        (nx, ny), or (Q, nx, ny) for a batch of distributions.
    """
    if max_steps < 0:
        raise TaskError(f"max_steps must be >= 0, got {max_steps}")
    q = np.full(4, 0.25) if probs is None else np.asarray(probs, np.float64)
    batch = q.ndim == 2
    q = q.reshape(-1, 4) if q.ndim in (1, 2) and q.shape[-1] == 4 else None  # type: ignore
    if q is None or (q < 0).any() or (np.abs(q.sum(1) - 1.0) > 1e-9).any():
        raise TaskError(f"probs must be 4 non-negative numbers summing to 1, got {probs}")
    nx, ny = blocked.shape
    nxt = _next_index(blocked)                                   # (4, n)
    t = target[0] * ny + target[1]
    p = np.zeros((len(q), nx * ny))
    p[:, t] = 1.0
    for _ in range(max_steps):
        p = np.einsum("qa,qan->qn", q, p[:, nxt])
        p[:, t] = 1.0
    out = p.reshape(len(q), nx, ny)
    return out if batch else out[0]


def start_success(tm: TaskMap, max_steps: int | None = None,
                  probs: Sequence[float] | np.ndarray | None = None) -> float | np.ndarray:
    """Success of a stationary random policy (or a (Q, 4) batch of them), averaged over
    the env's start cells."""
    cap = tm.task.max_steps if max_steps is None else max_steps
    starts = tm.start_cells(cap)
    if not starts:
        raise TaskError(f"task {tm.task.name!r} has no start cell within {cap} steps")
    p = success_within(tm.blocked, tm.task.target_cell, cap, probs)
    xs, ys = np.array(starts).T
    vals = p[..., xs, ys].mean(-1)
    return vals if np.ndim(vals) else float(vals)


def simplex_grid(grid: int) -> np.ndarray:
    """(Q, 4) every action distribution with probabilities in steps of 1/``grid``."""
    rows = [(a, b, c, grid - a - b - c) for a, b, c in
            itertools.product(range(grid + 1), repeat=3) if a + b + c <= grid]
    return np.array(rows, np.float64) / grid


def best_blind(tm: TaskMap, max_steps: int | None = None, grid: int = 20
               ) -> tuple[float, tuple[float, ...]]:
    """The best view-blind policy (a stationary action distribution: knows the target,
    ignores the view) on a simplex grid of step 1/``grid``: (success, q).

    Distributions are evaluated in chunks so memory stays under ~100 MB on large lattices.
    """
    qs = simplex_grid(grid)
    n = tm.blocked.size
    chunk = max(1, int(100e6 // (8 * 5 * n)))
    vals = np.concatenate([np.atleast_1d(start_success(tm, max_steps, qs[i:i + chunk]))
                           for i in range(0, len(qs), chunk)])
    i = int(np.argmax(vals))
    return float(vals[i]), tuple(float(v) for v in qs[i])


@dataclass(frozen=True)
class TaskDifficulty:
    """What chance achieves on a task (all exact, from the DP above)."""

    random_walk_sr: float
    """Success of a uniform random walk within max_steps, mean over the start cells."""
    blind_sr: float
    """View-blind success: the best stationary action distribution (simplex grid of step
    0.05), a policy that knows the target and ignores the current view."""
    blind_probs: tuple[float, ...]
    """That distribution (north, east, west, south)."""
    mean_shortest_path: float
    """Mean BFS shortest path from the start cells, in lattice steps."""
    n_starts: int
    """Number of valid start cells."""
    max_steps: int
    """The cap the figures are for."""

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["blind_probs"] = list(self.blind_probs)
        return d


def task_difficulty(tm: TaskMap, max_steps: int | None = None,
                    blind_grid: int = 20) -> TaskDifficulty:
    """All figures of :class:`TaskDifficulty` for a bound task."""
    cap = tm.task.max_steps if max_steps is None else max_steps
    starts = tm.start_cells(cap)
    if not starts:
        raise TaskError(f"task {tm.task.name!r} has no start cell within {cap} steps")
    blind, q = best_blind(tm, cap, blind_grid) if blind_grid else (float("nan"), ())
    return TaskDifficulty(
        random_walk_sr=float(start_success(tm, cap)), blind_sr=blind, blind_probs=tuple(q),
        mean_shortest_path=float(np.mean([tm.dist_to_target[c] for c in starts])),
        n_starts=len(starts), max_steps=int(cap))


def set_difficulty(maps: Sequence[TaskMap], max_steps: int | Sequence[int] | None = None,
                   blind_grid: int = 20) -> dict[str, Any]:
    """Per-task figures and their means over a task set (tasks weighted equally, as the
    env samples tasks uniformly): ``{"tasks": {name: {...}}, "random_walk_sr": ...}``.

    ``max_steps``: one cap for all, one per task, or None for each task's own."""
    caps = list(max_steps) if isinstance(max_steps, Sequence) else [max_steps] * len(maps)
    per: dict[str, TaskDifficulty] = {}
    memo: dict[bytes, TaskDifficulty] = {}  # the figures depend on these alone: the
    for tm, cap in zip(maps, caps, strict=True):  # altitudes of a whole-scene set share them
        c = tm.task.max_steps if cap is None else cap
        shape_target = (tm.blocked.shape, tm.task.target_cell, c, blind_grid)
        key = b"|".join([tm.blocked.tobytes(), np.asarray(tm.start_cells(c)).tobytes(),
                         str(shape_target).encode()])
        if key not in memo:
            memo[key] = task_difficulty(tm, c, blind_grid)
        per[tm.task.name] = memo[key]
    vals = list(per.values())
    return {"tasks": {k: v.to_dict() for k, v in per.items()},
            "random_walk_sr": float(np.mean([v.random_walk_sr for v in vals])),
            "blind_sr": float(np.mean([v.blind_sr for v in vals])),
            "mean_shortest_path": float(np.mean([v.mean_shortest_path for v in vals]))}


def env_difficulty(env: Any, blind_grid: int = 20) -> dict[str, Any]:
    """:func:`set_difficulty` of a GeoNavEnv's tasks at the env's own episode caps."""
    u = env.unwrapped
    return set_difficulty(u.task_maps, [u.max_steps_of(i) for i in range(len(u.task_maps))],
                          blind_grid)


def taskset_difficulty(ts: Any, scene: Any, blind_grid: int = 20) -> dict[str, Any]:
    """:func:`set_difficulty` of a :class:`geonav.tasks.TaskSet` on its scene (the value
    ``geonav tasks make`` stores in the task set's ``meta["difficulty"]``)."""
    ts.check_scene(scene)
    return set_difficulty([bind(t, scene, ts.camera) for t in ts.tasks], None, blind_grid)


def blind_at_most(tm: TaskMap, limit: float, max_steps: int | None = None,
                  grid: int = 20) -> bool:
    """True when the task's view-blind success (:func:`best_blind` on the grid of step
    1/``grid``) is at most ``limit``.

    A coarse grid (step 1/4, 35 distributions) is tried first: its best is a lower bound of
    the fine grid's (every coarse point lies on the fine grid when 4 divides ``grid``), so a
    task above the limit there is refused without the full search.
    """
    if grid % 4 == 0:
        coarse = np.atleast_1d(start_success(tm, max_steps, simplex_grid(4)))
        if float(coarse.max()) > limit:
            return False
    return best_blind(tm, max_steps, grid)[0] <= limit


def chance_floor(random_walk_sr: float, blind_sr: float | None = None) -> float:
    """The lowest threshold a convergence rule may use on a task set: the larger chance
    line (random walk, view-blind) plus half its gap to 1 (ALGORITHMS.md (f))."""
    chance = max(random_walk_sr, blind_sr if blind_sr is not None else 0.0)
    return chance + (1.0 - chance) / 2.0


def describe(diff: dict[str, Any]) -> str:
    """One line for people: chance figures of a task set."""
    return (f"random-walk success {diff['random_walk_sr']:.3f}, best view-blind (knows the "
            f"target, ignores the view) {diff['blind_sr']:.3f}, mean shortest path "
            f"{diff['mean_shortest_path']:.1f} steps")
