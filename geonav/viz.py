"""Pictures of scenes, tasks, camera footprints and tracks (matplotlib, Agg)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from geonav.camera import Camera
from geonav.errors import ConfigError
from geonav.scene import Scene
from geonav.tasks import Cell, NavTask, TaskSet

FOOTPRINT_ALTS_M = (300.0, 75.0, 45.0, 15.0)


def draw_scene(
    scene: Scene,
    out: str | os.PathLike[str],
    *,
    tasks: TaskSet | Sequence[NavTask] | None = None,
    tracks: Sequence[tuple[NavTask, Sequence[Cell], str]] = (),
    footprints_at: Sequence[float] = FOOTPRINT_ALTS_M,
    camera: Camera | None = None,
    title: str | None = None,
    max_px: int = 1600,
    bounds_m: tuple[float, float, float, float] | None = None,
    dpi: int = 120,
) -> Path:
    """Draw the scene with task regions, targets, camera footprints and tracks to a PNG.

    Args:
        scene: the scene.
        out: PNG path.
        tasks: task regions (rectangles) and targets (stars) to draw.
        tracks: (task, cells visited, label) triples drawn as lines on the lattice.
        footprints_at: altitudes whose camera footprints are drawn around the first
            task's target (or the scene centre).
        camera: the camera (footprint sizes).
        title: figure title.
        max_px: the scene image is downsampled to at most this many pixels across.
        bounds_m: (xmin, ymin, xmax, ymax) in scene metres to show instead of the whole
            scene (clipped to the scene); only that part of the image is drawn.
        dpi: figure resolution (the PNG's size grows with its square).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    camera = camera or (tasks.camera if isinstance(tasks, TaskSet) else Camera())
    task_list = list(tasks.tasks if isinstance(tasks, TaskSet) else (tasks or []))
    sx0, sy0, sx1, sy1 = scene.bounds_m
    xmin, ymin, xmax, ymax = _shown_bounds(scene, bounds_m)
    # Pixel window of the shown part (row 0 is the north edge).
    c0 = int(np.floor((xmin - sx0) / scene.gsd_m))
    c1 = int(np.ceil((xmax - sx0) / scene.gsd_m))
    r0 = int(np.floor((sy1 - ymax) / scene.gsd_m))
    r1 = int(np.ceil((sy1 - ymin) / scene.gsd_m))
    step = max(1, int(np.ceil(max(c1 - c0, r1 - r0) / max_px)))
    w_m, h_m = xmax - xmin, ymax - ymin
    fig, ax = plt.subplots(figsize=(9, 9 * h_m / w_m + 0.6), dpi=dpi)
    ax.imshow(scene.rgb[r0:r1:step, c0:c1:step],
              extent=(sx0 + c0 * scene.gsd_m, sx0 + c1 * scene.gsd_m,
                      sy1 - r1 * scene.gsd_m, sy1 - r0 * scene.gsd_m),
              interpolation="none")
    if scene.dsm is not None and footprints_at:
        tall = scene.dsm >= min(footprints_at) - 5.0
        if tall.any():
            ys, xs = np.nonzero(tall[::step * 4, ::step * 4])
            ax.scatter(xmin + (xs + 0.5) * step * 4 * scene.gsd_m,
                       ymax - (ys + 0.5) * step * 4 * scene.gsd_m, s=1, c="magenta",
                       alpha=0.25, label=f"surface > {min(footprints_at) - 5:g} m")
    colours = plt.cm.tab20(np.linspace(0, 1, max(1, len(task_list))))
    for task, colour in zip(task_list, colours, strict=False):
        x0, y0, x1, y1 = task.region_m
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=1.2, ec=colour))
        tgt = task.lattice.center(task.target_cell)
        ax.plot(tgt.x_m, tgt.y_m, marker="*", ms=11, mec="black", mfc=colour)
        ax.text(x0, y1, f" {task.name}", color=colour, fontsize=7, va="bottom", clip_on=True)
    _draw_footprints(ax, camera, footprints_at, task_list, (xmin, ymin, xmax, ymax))
    for task, cells, label in tracks:
        pts = np.array([[task.lattice.center(c).x_m, task.lattice.center(c).y_m] for c in cells])
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], "-o", ms=2.5, lw=1.5, label=label)
            ax.plot(*pts[0], "s", ms=7, mfc="lime", mec="black")
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title or f"scene {scene.name}: {scene.width}x{scene.height} px at "
                 f"{scene.gsd_m:g} m/px")
    if tracks or (scene.dsm is not None and footprints_at):
        ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    try:
        return save_figure(fig, out)
    finally:
        plt.close(fig)


def _shown_bounds(scene: Scene, bounds_m: tuple[float, float, float, float] | None
                  ) -> tuple[float, float, float, float]:
    """The part of the scene to draw (scene metres): ``bounds_m`` clipped to the scene, or
    all of it; ValueError when they do not overlap."""
    sx0, sy0, sx1, sy1 = scene.bounds_m
    if bounds_m is None:
        return sx0, sy0, sx1, sy1
    xmin, ymin = max(bounds_m[0], sx0), max(bounds_m[1], sy0)
    xmax, ymax = min(bounds_m[2], sx1), min(bounds_m[3], sy1)
    if xmax <= xmin or ymax <= ymin:
        raise ValueError(f"bounds_m {bounds_m} do not overlap the scene {scene.bounds_m}")
    return xmin, ymin, xmax, ymax


def _draw_footprints(ax: Any, camera: Camera, footprints_at: Sequence[float],
                     task_list: list[NavTask], shown: tuple[float, float, float, float]) -> None:
    """Camera footprints at each altitude around the first task's target (or the centre
    of what is shown), labelled inside the axes."""
    from matplotlib.patches import Rectangle

    xmin, ymin, xmax, ymax = shown
    centre = (task_list[0].lattice.center(task_list[0].target_cell) if task_list
              else None)
    cx, cy = (centre.x_m, centre.y_m) if centre else ((xmin + xmax) / 2, (ymin + ymax) / 2)
    for alt, style in zip(footprints_at, ("-", "--", "-.", ":"), strict=False):
        side = camera.footprint_m(alt)
        ax.add_patch(Rectangle((cx - side / 2, cy - side / 2), side, side, fill=False,
                               ls=style, lw=1.0, ec="white"))
        # Labels stay inside the axes (a footprint wider than a small scene would put its
        # label outside, and tight_layout would then squash the picture to make room).
        lx = min(max(cx - side / 2, xmin), xmax)
        ly = min(cy + side / 2, ymax)
        ax.text(lx, ly, f"{alt:g} m view", color="white", fontsize=7,
                va="bottom" if ly < ymax else "top", clip_on=True)


def save_figure(fig: Any, out: str | os.PathLike[str]) -> Path:
    """Save a matplotlib figure atomically (temp sibling, then rename), marked as geonav's.

    Raises:
        ConfigError: matplotlib cannot write pictures of ``out``'s suffix.
    """
    from geonav.outputs import PICTURE_METADATA

    out = Path(out)
    fmt = out.suffix.lower().lstrip(".")
    known = fig.canvas.get_supported_filetypes()
    if fmt not in known:
        raise ConfigError(f"{out}: cannot draw a '.{fmt}' picture; end the name in one of "
                          f"{', '.join('.' + k for k in sorted(known))}")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        fig.savefig(tmp, format=fmt, metadata=PICTURE_METADATA.get(fmt))
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out
