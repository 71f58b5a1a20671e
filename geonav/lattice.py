"""The lattice of a navigation task: cells, obstacles, shortest paths, task records.

A task is a square (or rectangular) region of the scene, a lattice step in
metres, a flight altitude, a target cell and an episode cap (:class:`NavTask`).
The lattice is the same at every altitude, so a cell means the same place at
300, 75, 45 and 15 m; only the view and the obstacles change (DESIGN.md
"Environment"). :func:`bind` checks a task against a scene and gives its
:class:`TaskMap` (obstacles, BFS distances to the target, view coverage), the
input of :mod:`geonav.difficulty`, :mod:`geonav.env` and :mod:`geonav.vecenv`.
Task sets and sampling live in :mod:`geonav.tasks`, which re-exports these names.

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

import math
import numbers
from collections import deque
from dataclasses import asdict, dataclass, field
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
