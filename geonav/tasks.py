"""Navigation tasks: a lattice of positions in a region, obstacles, shortest paths.

A task is a square (or rectangular) region of the scene, a lattice step in
metres, a flight altitude, a target cell and an episode cap. The lattice is
the same at every altitude, so a cell means the same place at 300, 75, 45 and
15 m; only the view and the obstacles change (DESIGN.md "Environment").

Cells are ``(ix, iy)`` with ``ix`` counting east and ``iy`` counting north
from the region's south-west corner; cell centres sit half a step inside.
Per-cell grids are numpy arrays of shape ``(nx, ny)`` indexed ``[ix, iy]``.

Obstacles at altitude ``h``: a cell is blocked when the DSM within
``safety_radius_m`` of its centre rises above ``h - clearance_m``.

Imagery coverage: a cell is a valid target or start only when the camera view
from ``h`` above it has at least ``min_coverage`` (default 99 %) valid imagery
(:func:`view_coverage`); the rest of the lattice can still be flown over.
"""

from __future__ import annotations

import hashlib
import json
import math
import numbers
import os
import tempfile
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geonav.camera import Camera
from geonav.errors import TaskError
from geonav.geo import ScenePoint
from geonav.scene import Scene

Cell = tuple[int, int]
Region = tuple[float, float, float, float]

#: Action index -> lattice move (dx, dy): forward = north, right = east (DESIGN.md "Frames").
ACTION_MOVES: tuple[Cell, ...] = ((0, 1), (1, 0), (-1, 0), (0, -1))
ACTION_MEANINGS: tuple[str, ...] = ("forward", "right", "left", "backward")
TASKSET_SCHEMA = 1
#: Most cells one task's lattice may have (1000 x 1000): every cell gets a rendered view
#: per altitude (21 KiB at 84 px), an obstacle test and BFS distances.
MAX_LATTICE_CELLS = 1_000_000
#: Highest flight altitude (m) a task may ask for: far above any drone's ceiling, low enough
#: that a view still sees the scene.
MAX_ALT_M = 10_000.0
#: Least fraction of valid imagery in a target's or start's view (item 5 of issue 13).
DEFAULT_MIN_COVERAGE = 0.99


@dataclass(frozen=True)
class Lattice:
    """Cells of ``step_m`` metres covering ``region_m`` = (xmin, ymin, xmax, ymax)."""

    region_m: Region
    step_m: float

    def __post_init__(self) -> None:
        if len(self.region_m) != 4 or not all(
                isinstance(v, numbers.Real) and math.isfinite(v) for v in self.region_m):
            raise TaskError(f"region {self.region_m} must be 4 finite numbers "
                            "(xmin, ymin, xmax, ymax) in scene metres")
        xmin, ymin, xmax, ymax = self.region_m
        if not (self.step_m > 0 and math.isfinite(self.step_m)):
            raise TaskError(f"lattice step must be a positive number of metres, got "
                            f"{self.step_m}")
        if xmax - xmin < self.step_m or ymax - ymin < self.step_m:
            raise TaskError(f"region {self.region_m} is smaller than one {self.step_m} m step")
        # Before anything sized by the lattice is allocated (obstacle maps, BFS, views).
        n = (xmax - xmin) / self.step_m * ((ymax - ymin) / self.step_m)
        if n > MAX_LATTICE_CELLS:
            need = self.step_m * math.sqrt(n / MAX_LATTICE_CELLS)
            raise TaskError(
                f"a {self.step_m:g} m lattice over {xmax - xmin:.0f} x {ymax - ymin:.0f} m has "
                f"{n:,.0f} cells, more than the {MAX_LATTICE_CELLS:,} one task may have (its "
                f"views alone would take {n * 84 * 84 * 3 / (1 << 30):,.0f} GiB at 84 px); use "
                f"a step of at least {need:.3g} m")

    @property
    def shape(self) -> tuple[int, int]:
        """(nx, ny): cells east and north."""
        xmin, ymin, xmax, ymax = self.region_m
        return (int(math.floor((xmax - xmin) / self.step_m + 1e-9)),
                int(math.floor((ymax - ymin) / self.step_m + 1e-9)))

    @property
    def n_cells(self) -> int:
        nx, ny = self.shape
        return nx * ny

    def contains(self, cell: Cell) -> bool:
        nx, ny = self.shape
        return 0 <= cell[0] < nx and 0 <= cell[1] < ny

    def center(self, cell: Cell) -> ScenePoint:
        """The scene point at the centre of ``cell``."""
        xmin, ymin, _, _ = self.region_m
        return ScenePoint(xmin + (cell[0] + 0.5) * self.step_m,
                          ymin + (cell[1] + 0.5) * self.step_m)

    def cell_of(self, p: ScenePoint) -> Cell:
        """The cell whose square contains ``p`` (may lie outside the lattice)."""
        xmin, ymin, _, _ = self.region_m
        return (int(math.floor((p.x_m - xmin) / self.step_m)),
                int(math.floor((p.y_m - ymin) / self.step_m)))

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """(x_m, y_m) arrays of shape (nx, ny) of all cell centres."""
        nx, ny = self.shape
        xmin, ymin, _, _ = self.region_m
        xs = xmin + (np.arange(nx) + 0.5) * self.step_m
        ys = ymin + (np.arange(ny) + 0.5) * self.step_m
        return np.meshgrid(xs, ys, indexing="ij")


@dataclass(frozen=True)
class ObstacleModel:
    """How the DSM becomes blocked cells.

    Attributes:
        safety_radius_m: horizontal radius around a cell centre the vehicle needs free.
        clearance_m: vertical clearance kept above the surface.
    """

    safety_radius_m: float = 3.0
    clearance_m: float = 5.0


@dataclass(frozen=True)
class NavTask:
    """One navigation task.

    Attributes:
        name: unique name within its task set ("meta-03", "scene-15m").
        kind: "meta" (a sub-region at 300 m) or "scene" (whole-scene, low altitude).
        region_m: (xmin, ymin, xmax, ymax) of the lattice in scene metres.
        step_m: lattice step in metres (one action moves one step).
        alt_m: flight altitude above ground in metres.
        target_cell: the goal cell (ix, iy).
        max_steps: episode cap (70 in the paper's sub-region runs, 120 in the curriculum).
        obstacles: the obstacle model used with the scene's DSM.
        min_coverage: least fraction of valid imagery in the view of the target and
            of every start cell at ``alt_m``.
    """

    name: str
    kind: str
    region_m: Region
    step_m: float
    alt_m: float
    target_cell: Cell
    max_steps: int = 70
    obstacles: ObstacleModel = field(default_factory=ObstacleModel)
    min_coverage: float = DEFAULT_MIN_COVERAGE

    def __post_init__(self) -> None:
        self.lattice  # noqa: B018 - checks the region and step, and bounds the cells
        if not (0 < self.alt_m <= MAX_ALT_M and math.isfinite(self.alt_m)):
            raise TaskError(f"task {self.name!r}: altitude {self.alt_m} m must be within "
                            f"0..{MAX_ALT_M:g} m")
        if not 1 <= self.max_steps <= 1_000_000:
            raise TaskError(f"task {self.name!r}: max_steps {self.max_steps} must be within "
                            "1..1000000")

    @property
    def lattice(self) -> Lattice:
        return Lattice(self.region_m, self.step_m)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["region_m"], d["target_cell"] = list(self.region_m), list(self.target_cell)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NavTask:
        try:
            return cls(
                name=str(d["name"]), kind=str(d["kind"]),
                region_m=tuple(float(v) for v in d["region_m"]),  # type: ignore[arg-type]
                step_m=float(d["step_m"]), alt_m=float(d["alt_m"]),
                target_cell=(int(d["target_cell"][0]), int(d["target_cell"][1])),
                max_steps=int(d.get("max_steps", 70)),
                obstacles=ObstacleModel(**d.get("obstacles", {})),
                min_coverage=float(d.get("min_coverage", DEFAULT_MIN_COVERAGE)),
            )
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as err:
            raise TaskError(f"task {d.get('name', '?')!r} is malformed: {err!r}") from err

    def with_alt(self, alt_m: float, *, max_steps: int | None = None) -> NavTask:
        """The same lattice and target at another altitude (curriculum stages)."""
        return NavTask(f"{self.name.rsplit('@', 1)[0]}@{alt_m:g}m", self.kind, self.region_m,
                       self.step_m, alt_m, self.target_cell,
                       self.max_steps if max_steps is None else max_steps, self.obstacles,
                       self.min_coverage)


def blocked_cells(scene: Scene, lattice: Lattice, alt_m: float,
                  model: ObstacleModel = ObstacleModel()) -> np.ndarray:
    """(nx, ny) bool: cells whose safety disc has surface above ``alt_m - clearance``."""
    nx, ny = lattice.shape
    blocked = np.zeros((nx, ny), bool)
    if scene.dsm is None:
        return blocked
    limit = alt_m - model.clearance_m
    r_px = max(0, int(math.ceil(model.safety_radius_m / scene.gsd_m)))
    yy, xx = np.mgrid[-r_px:r_px + 1, -r_px:r_px + 1]
    disc = (xx * xx + yy * yy) * scene.gsd_m ** 2 <= model.safety_radius_m ** 2 + 1e-9
    dsm = scene.dsm
    xs, ys = lattice.centers()
    for ix in range(nx):
        for iy in range(ny):
            col, row = scene.to_pixel(float(xs[ix, iy]), float(ys[ix, iy]))
            c, r = int(math.floor(col)), int(math.floor(row))
            r0, r1, c0, c1 = r - r_px, r + r_px + 1, c - r_px, c + r_px + 1
            if r0 < 0 or c0 < 0 or r1 > dsm.shape[0] or c1 > dsm.shape[1]:
                continue  # outside the DSM: unknown, treated as free (the mask governs)
            patch = dsm[r0:r1, c0:c1][disc]
            if patch.size and np.nanmax(patch, initial=-np.inf) > limit:
                blocked[ix, iy] = True
    return blocked


def bfs_distances(blocked: np.ndarray, source: Cell) -> np.ndarray:
    """(nx, ny) int32 lattice steps from ``source`` over free cells; -1 = unreachable."""
    nx, ny = blocked.shape
    dist = np.full((nx, ny), -1, np.int32)
    if blocked[source]:
        return dist
    dist[source] = 0
    queue = deque([source])
    while queue:
        x, y = queue.popleft()
        d = dist[x, y] + 1
        for dx, dy in ACTION_MOVES:
            u, v = x + dx, y + dy
            if 0 <= u < nx and 0 <= v < ny and dist[u, v] < 0 and not blocked[u, v]:
                dist[u, v] = d
                queue.append((u, v))
    return dist


@dataclass
class TaskMap:
    """A task bound to a scene: obstacles, distances to the target, valid starts."""

    task: NavTask
    blocked: np.ndarray
    dist_to_target: np.ndarray
    coverage: np.ndarray | None = None

    @property
    def lattice(self) -> Lattice:
        return self.task.lattice

    def start_cells(self, max_steps: int | None = None) -> list[Cell]:
        """Free cells from which the target is reachable within the cap (target excluded)
        and whose view has at least the task's ``min_coverage`` of valid imagery."""
        cap = self.task.max_steps if max_steps is None else max_steps
        ok = (self.dist_to_target > 0) & (self.dist_to_target <= cap)
        if self.coverage is not None:
            ok &= self.coverage >= self.task.min_coverage
        return [(int(x), int(y)) for x, y in zip(*np.nonzero(ok), strict=True)]

    def shortest_path_action(self, cell: Cell) -> int:
        """An action that moves one step closer to the target (the BFS oracle)."""
        d = self.dist_to_target[cell]
        for a, (dx, dy) in enumerate(ACTION_MOVES):
            nxt = (cell[0] + dx, cell[1] + dy)
            if self.lattice.contains(nxt) and 0 <= self.dist_to_target[nxt] < d:
                return a
        raise TaskError(f"no move from {cell} gets closer to target {self.task.target_cell}")


def view_margin_m(alt_m: float, camera: Camera) -> float:
    """Half the camera footprint: how far imagery must extend around a region."""
    return camera.footprint_m(alt_m) / 2.0


def view_coverage(scene: Scene, lattice: Lattice, alt_m: float, camera: Camera) -> np.ndarray:
    """(nx, ny) fraction of valid imagery in the camera view centred on each cell.

    The view is the footprint square at ``alt_m``; pixels outside the scene count
    as missing. Summed-area table of the mask, reduced so a footprint spans about
    256 blocks (error under 0.5 %), over the window the lattice's views cover.
    """
    foot = camera.footprint_m(alt_m)
    half = foot / 2
    xmin, ymin, xmax, ymax = lattice.region_m
    rs, cs = scene.window((xmin - half, ymin - half, xmax + half, ymax + half))
    f = max(1, int(foot / scene.gsd_m / 256))
    m = scene.mask[rs, cs]
    h, w = -(-m.shape[0] // f), -(-m.shape[1] // f)
    padded = np.zeros((h * f, w * f), np.float32)
    padded[:m.shape[0], :m.shape[1]] = m
    blocks = padded.reshape(h, f, w, f).mean(axis=(1, 3))
    sat = np.zeros((h + 1, w + 1), np.float64)
    sat[1:, 1:] = blocks.cumsum(0).cumsum(1)
    block_m = scene.gsd_m * f
    x0 = scene.transform.c + (cs.start or 0) * scene.gsd_m
    y0 = scene.transform.f - (rs.start or 0) * scene.gsd_m
    xs, ys = lattice.centers()
    c0 = np.rint((xs - half - x0) / block_m).astype(np.int64)
    c1 = np.rint((xs + half - x0) / block_m).astype(np.int64)
    r0 = np.rint((y0 - (ys + half)) / block_m).astype(np.int64)
    r1 = np.rint((y0 - (ys - half)) / block_m).astype(np.int64)
    area = np.maximum((c1 - c0) * (r1 - r0), 1)
    c0, c1 = np.clip(c0, 0, w), np.clip(c1, 0, w)
    r0, r1 = np.clip(r0, 0, h), np.clip(r1, 0, h)
    count = sat[r1, c1] - sat[r0, c1] - sat[r1, c0] + sat[r0, c0]
    return np.clip(count / area, 0.0, 1.0)


def bind(task: NavTask, scene: Scene, camera: Camera | None = None) -> TaskMap:
    """Check ``task`` against ``scene`` and compute its obstacles and distances.

    Raises:
        TaskError: region outside the scene or without its view margin, target
            outside the lattice, on an obstacle, unreachable from every cell, or with
            less than ``task.min_coverage`` valid imagery in its view.
    """
    camera = camera or Camera()
    lattice = task.lattice
    xmin, ymin, xmax, ymax = task.region_m
    sx0, sy0, sx1, sy1 = scene.bounds_m
    margin = view_margin_m(task.alt_m, camera)
    if xmin < sx0 or ymin < sy0 or xmax > sx1 or ymax > sy1:
        raise TaskError(f"task {task.name!r}: region {task.region_m} lies outside scene "
                        f"{scene.name!r} bounds {tuple(round(v, 1) for v in scene.bounds_m)}")
    short = max(sx0 - (xmin - margin), sy0 - (ymin - margin),
                (xmax + margin) - sx1, (ymax + margin) - sy1)
    if short > 1e-6:
        raise TaskError(f"task {task.name!r}: region {task.region_m} needs {margin:.0f} m of "
                        f"imagery around it for its {task.alt_m:g} m view; it is {short:.1f} m "
                        "short. Move the region inward or lower the altitude")
    if not lattice.contains(task.target_cell):
        raise TaskError(f"task {task.name!r}: target {task.target_cell} is outside the "
                        f"{lattice.shape} lattice")
    blocked = blocked_cells(scene, lattice, task.alt_m, task.obstacles)
    if blocked[task.target_cell]:
        raise TaskError(f"task {task.name!r}: target {task.target_cell} is an obstacle at "
                        f"{task.alt_m:g} m; pick another target cell")
    dist = bfs_distances(blocked, task.target_cell)
    if not (dist > 0).any():
        raise TaskError(f"task {task.name!r}: target {task.target_cell} is unreachable from "
                        f"every cell at {task.alt_m:g} m")
    if not 0.0 <= task.min_coverage <= 1.0:
        raise TaskError(f"task {task.name!r}: min_coverage {task.min_coverage} must be "
                        "within 0..1")
    coverage = view_coverage(scene, lattice, task.alt_m, camera)
    if coverage[task.target_cell] < task.min_coverage:
        raise TaskError(f"task {task.name!r}: the {task.alt_m:g} m view of target "
                        f"{task.target_cell} has only {coverage[task.target_cell]:.0%} valid "
                        f"imagery, under the {task.min_coverage:.0%} required; pick a target "
                        "inside the imagery")
    tm = TaskMap(task, blocked, dist, coverage)
    if not tm.start_cells():
        raise TaskError(f"task {task.name!r}: no start cell within {task.max_steps} steps of "
                        f"the target has {task.min_coverage:.0%} valid imagery in its "
                        f"{task.alt_m:g} m view")
    return tm


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
    obstacles: ObstacleModel = ObstacleModel(),
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
    obstacles: ObstacleModel = ObstacleModel(),
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
    from geonav.difficulty import blind_at_most, start_success

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
