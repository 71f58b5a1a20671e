"""Navigation task sets: the JSON file of a scene's tasks and the samplers that make them.

:class:`TaskSet` is the tasks of one scene with the camera their margins were checked
for, saved as JSON. :func:`sample_meta_tasks` draws the paper's meta-tasks (regions
snapped to the GSD, kept far enough inside the imagery for the highest altitude's
view); :func:`whole_scene_tasks` makes full-scene targets; both can keep only tasks
whose chance success (:mod:`geonav.difficulty`) stays under a limit.

The lattice itself (cells, obstacles, shortest paths, :class:`NavTask`,
:class:`TaskMap`, :func:`bind`) lives in :mod:`geonav.lattice`; its names are
re-exported here, where most callers import them from.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geonav.camera import Camera
from geonav.difficulty import blind_at_most, start_success
from geonav.errors import TaskError
from geonav.lattice import (
    ACTION_MEANINGS,
    ACTION_MOVES,
    DEFAULT_MIN_COVERAGE,
    MAX_ALT_M,
    MAX_LATTICE_CELLS,
    Cell,
    Lattice,
    NavTask,
    ObstacleModel,
    Region,
    TaskMap,
    bfs_distances,
    bind,
    blocked_cells,
    view_coverage,
    view_margin_m,
)
from geonav.scene import Scene

__all__ = [
    "ACTION_MEANINGS", "ACTION_MOVES", "DEFAULT_MIN_COVERAGE", "MAX_ALT_M",
    "MAX_LATTICE_CELLS", "TASKSET_SCHEMA", "Cell", "Lattice", "NavTask", "ObstacleModel",
    "Region", "TaskMap", "TaskSet", "bfs_distances", "bind", "blocked_cells",
    "sample_meta_tasks", "starts_on_every_side", "view_coverage", "view_margin_m",
    "whole_scene_tasks",
]

TASKSET_SCHEMA = 1


@dataclass
class TaskSet:
    """Tasks on one scene, saved as JSON.

    Attributes:
        scene_name: the scene's name.
        scene_id: :attr:`geonav.scene.Scene.scene_id` of the scene the tasks were made on.
        tasks: the tasks.
        camera: the camera the margins were checked for.
        meta: provenance (sampler, seed, ...).
    """

    scene_name: str
    scene_id: str
    tasks: list[NavTask]
    camera: Camera = field(default_factory=Camera)
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.tasks)

    def __getitem__(self, i: int) -> NavTask:
        return self.tasks[i]

    def check_scene(self, scene: Scene) -> None:
        if scene.scene_id != self.scene_id:
            raise TaskError(f"this task set was made for scene {self.scene_name!r} "
                            f"(id {self.scene_id}), not for scene {scene.name!r} "
                            f"(id {scene.scene_id}); make tasks for it with 'geonav tasks make'")

    def to_dict(self) -> dict[str, Any]:
        return dict(schema_version=TASKSET_SCHEMA, scene_name=self.scene_name,
                    scene_id=self.scene_id, camera=asdict(self.camera), meta=self.meta,
                    tasks=[t.to_dict() for t in self.tasks])

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write atomically (temp file + rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(self.to_dict(), f, indent=1, allow_nan=False)
            os.replace(tmp, path)
        except ValueError as err:  # NaN/inf is not JSON
            Path(tmp).unlink(missing_ok=True)
            raise TaskError(f"task set for {self.scene_name!r} holds a non-finite number "
                            f"({err}); nothing written to {path}") from err
        except BaseException:
            Path(tmp).unlink(missing_ok=True)  # nothing half-written
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> TaskSet:
        path = Path(path)
        try:
            d = json.loads(Path(path).read_text())
        except FileNotFoundError as err:
            raise TaskError(f"task file {path} does not exist; make one with "
                            "'geonav tasks make'") from err
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise TaskError(f"task file {path} is not valid JSON: {err}") from err
        if not isinstance(d, dict) or d.get("schema_version") != TASKSET_SCHEMA:
            raise TaskError(f"task file {path} has schema_version "
                            f"{d.get('schema_version') if isinstance(d, dict) else None}, "
                            f"expected {TASKSET_SCHEMA}")
        if not isinstance(d.get("meta", {}), dict):
            raise TaskError(f"task file {path}: 'meta' must be an object, got "
                            f"{type(d['meta']).__name__}; re-create it with 'geonav tasks make'")
        try:
            tasks = [NavTask.from_dict(t) for t in d["tasks"]]
            camera = Camera(**d.get("camera", {}))
            ts = cls(str(d["scene_name"]), str(d["scene_id"]), tasks, camera, d.get("meta", {}))
        except TaskError as err:  # a task's numbers out of bounds: name the file too
            raise TaskError(f"task file {path}: {err}") from err
        except KeyError as err:
            raise TaskError(f"task file {path} is malformed: missing {err}") from err
        except (TypeError, ValueError, AttributeError) as err:
            raise TaskError(f"task file {path} is malformed: {err}") from err
        if not tasks:
            raise TaskError(f"task file {path} holds no tasks")
        names = [t.name for t in tasks]
        if len(set(names)) != len(names):
            raise TaskError(f"task file {path} has duplicate task names")
        return ts

    @property
    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


def _snap(v: float, step: float) -> float:
    return round(v / step) * step


def sample_meta_tasks(
    scene: Scene,
    count: int = 15,
    *,
    size_m: float = 150.0,
    alt_m: float = 300.0,
    step_m: float = 15.0,
    max_steps: int = 70,
    seed: int = 0,
    camera: Camera | None = None,
    margin_alt_m: float | None = None,
    obstacles: ObstacleModel = ObstacleModel(),  # noqa: B008 (frozen: immutable)
    max_overlap: float = 0.5,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    max_random_walk: float | None = None,
    max_blind: float | None = None,
    progress: Callable[[str, float], None] | None = None,
) -> TaskSet:
    """Sample ``count`` meta-tasks: square regions of ``size_m`` at ``alt_m``.

    Regions are snapped to the scene GSD, kept inside the valid imagery with the
    margin the view from ``margin_alt_m`` (default ``alt_m``) needs, overlap
    each other by at most ``max_overlap`` of their area, and get a random free,
    reachable target whose view at ``alt_m`` has at least ``min_coverage`` valid
    imagery (starts are held to the same). With ``max_random_walk``, a target is kept
    only when a uniform random walk succeeds from the task's starts at most that often
    (:func:`geonav.difficulty.start_success`; a task that chance solves cannot show
    learning). With ``max_blind``, a target is kept only when the best *view-blind*
    policy (a stationary action distribution: knows the target, ignores the current view)
    succeeds at most that often, and when the task has start cells on every side of the
    target (west, east, south and north of it): a target in a region corner, which a
    fixed diagonal bias reaches from every start, is refused, so the kept tasks need the
    view (ALGORITHMS.md (f); 0.3 is the default for a learning comparison). Targets are
    drawn uniformly over the free cells either way. Reproducible by ``seed``.
    ``progress``: callback (phase, fraction), phase "meta-tasks" (tasks placed / count).
    """
    report = progress or (lambda phase, fraction: None)
    camera = camera or Camera()
    _check_chance_limit(max_random_walk)
    _check_chance_limit(max_blind, "max_blind")
    if count < 1:
        raise TaskError(f"count must be >= 1, got {count}")
    rng = np.random.default_rng(seed)
    margin = view_margin_m(margin_alt_m or alt_m, camera)
    sx0, sy0, sx1, sy1 = scene.bounds_m
    lo_x, hi_x = sx0 + margin, sx1 - margin - size_m
    lo_y, hi_y = sy0 + margin, sy1 - margin - size_m
    if hi_x < lo_x or hi_y < lo_y:
        need = 2 * margin + size_m
        raise TaskError(
            f"scene {scene.name!r} is {scene.size_m[0]:.0f} x {scene.size_m[1]:.0f} m; a "
            f"{size_m:g} m task at {alt_m:g} m needs {need:.0f} m ({margin:.0f} m of view "
            "margin each side). Use a larger scene, smaller tasks or a lower altitude")
    tasks: list[NavTask] = []
    regions: list[Region] = []
    attempts = 0
    report("meta-tasks", 0.0)
    while len(tasks) < count:
        attempts += 1
        if attempts > 200 * count:
            chance = _limits_text(max_random_walk, max_blind)
            raise TaskError(f"could only place {len(tasks)} of {count} meta-tasks with at most "
                            f"{max_overlap:.0%} overlap{chance} in scene {scene.name!r}; ask "
                            "for fewer or allow more overlap")
        x0 = _snap(rng.uniform(lo_x, hi_x), scene.gsd_m)
        y0 = _snap(rng.uniform(lo_y, hi_y), scene.gsd_m)
        x0, y0 = min(max(x0, lo_x), hi_x), min(max(y0, lo_y), hi_y)
        region = (x0, y0, x0 + size_m, y0 + size_m)
        if any(_overlap(region, r) > max_overlap for r in regions):
            continue
        if not _valid_imagery(scene, region, margin):
            continue
        lattice = Lattice(region, step_m)
        blocked = blocked_cells(scene, lattice, alt_m, obstacles)
        covered = view_coverage(scene, lattice, alt_m, camera) >= min_coverage
        free = np.argwhere(~blocked & covered)
        if len(free) < 2:
            continue
        target = tuple(int(v) for v in free[rng.integers(len(free))])
        task = NavTask(f"meta-{len(tasks):02d}", "meta", region, step_m, alt_m,
                       (target[0], target[1]), max_steps, obstacles, min_coverage)
        try:
            tm = bind(task, scene, camera)
        except TaskError:
            continue
        if not _chance_ok(tm, max_random_walk, max_blind):
            continue
        tasks.append(task)
        regions.append(region)
        report("meta-tasks", len(tasks) / count)
    return TaskSet(scene.name, scene.scene_id, tasks, camera,
                   dict(sampler="meta", count=count, size_m=size_m, alt_m=alt_m, step_m=step_m,
                        seed=seed, margin_alt_m=margin_alt_m or alt_m,
                        min_coverage=min_coverage, max_overlap=max_overlap,
                        max_random_walk=max_random_walk, max_blind=max_blind))


def whole_scene_tasks(
    scene: Scene,
    alts_m: Sequence[float] = (75.0, 45.0, 15.0),
    *,
    step_m: float = 15.0,
    max_steps: int = 120,
    seed: int = 0,
    region_m: Region | None = None,
    size_m: float | None = None,
    camera: Camera | None = None,
    obstacles: ObstacleModel = ObstacleModel(),  # noqa: B008 (frozen: immutable)
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    max_random_walk: float | None = None,
    max_blind: float | None = None,
    progress: Callable[[str, float], None] | None = None,
) -> TaskSet:
    """One task per altitude on the same lattice with the same target (curriculum).

    The region defaults to the scene shrunk by the view margin of the highest
    altitude (or a centred square of ``size_m``). The target is a random cell
    that is free at every altitude, has at least ``min_coverage`` valid imagery
    in its view at every altitude, and lies in the largest connected free area at
    the lowest altitude; starts are held to the same coverage. With ``max_random_walk``
    the target is redrawn until a uniform random walk succeeds at most that often at
    every altitude, and with ``max_blind`` until the best view-blind policy succeeds at
    most that often at every altitude with start cells on every side of the target (see
    :func:`sample_meta_tasks`). ``progress``: callback (phase, fraction), phases
    "obstacles" (altitudes done) and "target" (candidate targets tried, of at most 200).
    """
    report = progress or (lambda phase, fraction: None)
    camera = camera or Camera()
    _check_chance_limit(max_random_walk)
    _check_chance_limit(max_blind, "max_blind")
    margin = view_margin_m(max(alts_m), camera)
    sx0, sy0, sx1, sy1 = scene.bounds_m
    if region_m is None:
        if size_m is not None:
            cx, cy = (sx0 + sx1) / 2, (sy0 + sy1) / 2
            h = size_m / 2
            region_m = (_snap(cx - h, scene.gsd_m), _snap(cy - h, scene.gsd_m),
                        _snap(cx - h, scene.gsd_m) + size_m, _snap(cy - h, scene.gsd_m) + size_m)
        else:
            x0, y0 = sx0 + margin, sy0 + margin
            nx = int((sx1 - margin - x0) // step_m)
            ny = int((sy1 - margin - y0) // step_m)
            if nx < 2 or ny < 2:
                raise TaskError(f"scene {scene.name!r} leaves no room for a whole-scene task "
                                f"with {margin:.0f} m of view margin")
            region_m = (x0, y0, x0 + nx * step_m, y0 + ny * step_m)
    lattice = Lattice(region_m, step_m)
    blocked_all = np.zeros(lattice.shape, bool)
    report("obstacles", 0.0)
    for i, alt in enumerate(alts_m):
        blocked_all |= blocked_cells(scene, lattice, alt, obstacles)
        blocked_all |= view_coverage(scene, lattice, alt, camera) < min_coverage
        report("obstacles", (i + 1) / len(alts_m))
    lowest = blocked_cells(scene, lattice, min(alts_m), obstacles)
    rng = np.random.default_rng(seed)
    # Largest free component at the lowest altitude.
    best: np.ndarray | None = None
    seen = np.zeros(lattice.shape, bool)
    for cell in map(tuple, np.argwhere(~lowest)):
        if seen[cell]:
            continue
        comp = bfs_distances(lowest, (int(cell[0]), int(cell[1]))) >= 0
        seen |= comp
        if best is None or comp.sum() > best.sum():
            best = comp
    if best is None:
        raise TaskError(f"every cell of region {region_m} is blocked at {min(alts_m):g} m")
    candidates = np.argwhere(best & ~blocked_all)
    if len(candidates) == 0:
        raise TaskError(f"no cell of region {region_m} is free, with {min_coverage:.0%} valid "
                        f"imagery in its view, at all of {list(alts_m)} m")
    memo: dict[bytes, bool] = {}  # altitudes with the same obstacles and starts share it
    for tried in range(200):
        report("target", tried / 200)
        target = tuple(int(v) for v in candidates[rng.integers(len(candidates))])
        tasks = [NavTask(f"scene@{alt:g}m", "scene", region_m, step_m, float(alt),
                         (target[0], target[1]), max_steps, obstacles, min_coverage)
                 for alt in alts_m]
        if all(_chance_ok(bind(task, scene, camera), max_random_walk, max_blind, memo)
               for task in tasks):
            report("target", 1.0)
            break
    else:
        limits = _limits_text(max_random_walk, max_blind).removeprefix(" and ")
        raise TaskError(f"no target of region {region_m} keeps {limits} within {max_steps} "
                        "steps; use a finer lattice or a smaller max_steps")
    return TaskSet(scene.name, scene.scene_id, tasks, camera,
                   dict(sampler="scene", alts_m=list(alts_m), step_m=step_m, seed=seed,
                        min_coverage=min_coverage, max_random_walk=max_random_walk,
                        max_blind=max_blind))


def _check_chance_limit(limit: float | None, name: str = "max_random_walk") -> None:
    if limit is not None and not 0.0 < limit <= 1.0:
        raise TaskError(f"{name} must lie in (0, 1], got {limit}")


def _limits_text(max_random_walk: float | None, max_blind: float | None) -> str:
    """' and ...' naming the chance limits a sampler could not meet (empty without any)."""
    parts = []
    if max_random_walk is not None:
        parts.append(f"random-walk success <= {max_random_walk:g} (more cells per region or "
                     "a smaller max_steps lower it)")
    if max_blind is not None:
        parts.append(f"view-blind success <= {max_blind:g} with start cells on every side "
                     "of the target (more cells per region or a smaller max_steps lower it)")
    return "".join(f" and {p}" for p in parts)


def starts_on_every_side(tm: TaskMap) -> bool:
    """True when the task has start cells west, east, south and north of its target (an
    interior target, not one on the region's edge or in its corner)."""
    starts = tm.start_cells()
    if not starts:
        return False
    xs, ys = np.array(starts).T
    tx, ty = tm.task.target_cell
    return bool((xs < tx).any() and (xs > tx).any() and (ys < ty).any() and (ys > ty).any())


def _chance_ok(tm: TaskMap, limit: float | None, max_blind: float | None = None,
               memo: dict[bytes, bool] | None = None) -> bool:
    """True when chance stays within the limits: a uniform random walk succeeds at most
    ``limit`` (None: any) and the best view-blind policy at most ``max_blind`` (None: any),
    with start cells on every side of the target. ``memo`` keeps the answer per
    (obstacles, starts, target, cap): the figures depend on nothing else, so the
    altitudes of a whole-scene task without a surface model share one computation."""
    if limit is None and max_blind is None:
        return True
    key = b""
    if memo is not None:
        shape_target = (tm.blocked.shape, tm.task.target_cell, tm.task.max_steps)
        key = b"|".join([tm.blocked.tobytes(), np.asarray(tm.start_cells()).tobytes(),
                         str(shape_target).encode()])
        if key in memo:
            return memo[key]
    try:
        ok = True
        if limit is not None and float(start_success(tm)) > limit:
            ok = False
        elif max_blind is not None:
            ok = starts_on_every_side(tm) and blind_at_most(tm, max_blind)
    except TaskError:  # no start cell within the cap
        ok = False
    if memo is not None:
        memo[key] = ok
    return ok


def _overlap(a: Region, b: Region) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    return w * h / ((a[2] - a[0]) * (a[3] - a[1]))


def _valid_imagery(scene: Scene, region: Region, margin: float, need: float = 0.99) -> bool:
    rs, cs = scene.window((region[0] - margin, region[1] - margin,
                           region[2] + margin, region[3] + margin))
    window = scene.mask[rs, cs]
    return window.size > 0 and float(window.mean()) >= need
