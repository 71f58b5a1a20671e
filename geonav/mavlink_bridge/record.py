"""The flight record: JSON lines of every step and event, and a PNG of the track.

``flight.jsonl`` holds one object per line, each with a ``kind``:
``header`` (settings, scene, origin, lattice), ``step`` (time, action,
target in scene metres and NED, measured position, arrival time, frame
latency, battery, safety events), ``event``, ``statustext`` (the autopilot's
own messages, folded as on the console), ``battery`` (the battery series:
percent and volts whenever they change) and ``result``. Rows may come from
the link's threads (the autopilot's texts), so writing is locked. ``track.png`` is zoomed
to the flight (the flown track, the start, the target and the step targets
plus a margin of two cells) and shows the scene image, the lattice cells,
the fence, the whole measured track (climb, steps, return and landing, each
phase in its own colour) drawn above the step markers.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)


class FlightRecorder:
    """Writes ``flight.jsonl`` into ``out_dir`` as the flight goes.

    A record is never overwritten: when ``out_dir`` already holds something (an earlier
    flight), the record goes to the first free ``out_dir-2``, ``out_dir-3``, ...
    (:attr:`out_dir` says which).

    Args:
        out_dir: folder for the record (created).
    """

    def __init__(self, out_dir: str | Path) -> None:
        from geonav.outputs import claim_new_folder

        self.out_dir, fd = claim_new_folder(out_dir, "flight.jsonl")
        if self.out_dir != Path(out_dir):
            log.warning("%s already holds a flight record; this flight goes to %s",
                        out_dir, self.out_dir)
        self.path = self.out_dir / "flight.jsonl"
        self._f = open(fd, "w", encoding="utf-8")  # noqa: SIM115 - closed by close()
        self._t0 = time.monotonic()
        self.track_xy: list[tuple[float, float]] = []
        self.track_phase: list[str] = []
        self.steps: list[dict[str, Any]] = []
        self.events: list[str] = []
        self._lock = threading.Lock()
        self._battery_row: tuple[float, float | None, float | None] | None = None

    def elapsed_s(self) -> float:
        """Seconds since the record started."""
        return time.monotonic() - self._t0

    def write(self, kind: str, **data: Any) -> None:
        """Append one JSON line."""
        row = {"kind": kind, "t_s": round(self.elapsed_s(), 3), **data}
        with self._lock:
            if self._f.closed:
                return
            self._f.write(json.dumps(row, default=_jsonable) + "\n")
            self._f.flush()
        if kind == "step":
            self.steps.append(row)

    def battery(self, pct: float | None, volts: float | None) -> None:
        """One point of the battery series: written when it changed (0.5 % or 0.05 V)
        or 10 s after the last one."""
        if pct is None and volts is None:
            return
        last = self._battery_row
        now = self.elapsed_s()
        if last is not None and now - last[0] < 10.0 and \
                _near(last[1], pct, 0.5) and _near(last[2], volts, 0.05):
            return
        self._battery_row = (now, pct, volts)
        self.write("battery", pct=pct, volts=None if volts is None else round(volts, 3))

    def event(self, text: str) -> None:
        """Record a safety or phase event."""
        self.events.append(text)
        self.write("event", text=text)

    def sample(self, x_m: float, y_m: float, phase: str = "autonomy", alt_m: float = 0.0) -> None:
        """A measured scene position (and its flight phase) for the track plot."""
        self.track_xy.append((x_m, y_m))
        self.track_phase.append(phase)

    def close(self) -> None:
        """Close the JSON lines file."""
        with self._lock:
            if not self._f.closed:
                self._f.close()

    def plot(
        self,
        scene: Any,
        lattice: Any | None,
        start: tuple[float, float] | None,
        target: tuple[float, float] | None,
        fence: Any | None = None,
    ) -> Path:
        """Write ``track.png``: scene, lattice, fence, track, start and target."""
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        view = _view_box(self, scene.bounds_m, lattice, start, target)
        fig, ax = plt.subplots(figsize=(7, 7), dpi=100)
        backdrop = _backdrop(scene, view)
        if backdrop is not None:
            ax.imshow(backdrop[0], extent=backdrop[1], origin="upper")
        if lattice is not None:
            lx0, ly0, _, _ = lattice.region_m
            nx, ny = lattice.shape
            step = lattice.step_m
            for i in range(nx + 1):
                ax.plot([lx0 + i * step] * 2, [ly0, ly0 + ny * step], color="w", lw=0.5, alpha=0.6)
            for j in range(ny + 1):
                ax.plot([lx0, lx0 + nx * step], [ly0 + j * step] * 2, color="w", lw=0.5, alpha=0.6)
        if fence is not None:
            ax.plot(
                [fence.xmin_m, fence.xmax_m, fence.xmax_m, fence.xmin_m, fence.xmin_m],
                [fence.ymin_m, fence.ymin_m, fence.ymax_m, fence.ymax_m, fence.ymin_m],
                color="orange",
                lw=1.5,
                ls="--",
                label="geofence",
            )
        targets = [s["target_scene"] for s in self.steps if s.get("target_scene")]
        if targets:
            t = np.asarray(targets)
            ax.scatter(t[:, 0], t[:, 1], s=14, color="yellow", zorder=3, label="step targets")
        if self.track_xy:
            xy = np.asarray(self.track_xy)
            phases = np.asarray(self.track_phase)
            colours = {
                "takeoff": "deepskyblue",
                "arming": "deepskyblue",
                "takeover": "violet",
                "autonomy": "red",
                "landing": "magenta",
            }
            for name in dict.fromkeys(self.track_phase):
                sel = phases == name
                ax.plot(
                    xy[sel, 0],
                    xy[sel, 1],
                    ".-",
                    ms=2,
                    color=colours.get(name, "red"),
                    lw=1.5,
                    zorder=5,
                    label=f"flown track: {name}",
                )
        if start is not None:
            ax.scatter(
                [start[0]], [start[1]], marker="o", s=80, color="cyan", zorder=4, label="start"
            )
        if target is not None:
            ax.scatter(
                [target[0]], [target[1]], marker="*", s=200, color="lime", zorder=4, label="target"
            )
        ax.set_xlim(view[0], view[2])
        ax.set_ylim(view[1], view[3])
        ax.set_xlabel("x east (m)")
        ax.set_ylabel("y north (m)")
        ax.set_title(f"geonav flight over {getattr(scene, 'name', 'scene')}")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper right", fontsize=8)
        png = self.out_dir / "track.png"
        fig.savefig(png, bbox_inches="tight")
        plt.close(fig)
        return png


def _backdrop(scene: Any, view: tuple[float, float, float, float], max_px: int = 1400
              ) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
    """The scene image under ``view`` (scene metres), every k-th pixel so that its longer
    side is at most ``max_px``, and its extent (xmin, xmax, ymin, ymax); None when the view
    misses the scene. The plot showed the whole ortho before: matplotlib resampled a 2.5 km
    scene at 0.25 m (300 MB) for a 700 px picture, 30-70 s on a loaded machine."""
    rs, cs = scene.window(view)
    if rs.stop <= rs.start or cs.stop <= cs.start:
        return None
    k = max(1, math.ceil(max(rs.stop - rs.start, cs.stop - cs.start) / max_px))
    img = np.asarray(scene.rgb[rs.start:rs.stop:k, cs.start:cs.stop:k])
    x0, y1 = scene.transform.c, scene.transform.f  # the north-west corner
    g = scene.gsd_m
    extent = (x0 + cs.start * g, x0 + (cs.start + img.shape[1] * k) * g,
              y1 - (rs.start + img.shape[0] * k) * g, y1 - rs.start * g)
    return img, extent


def _view_box(
    rec: FlightRecorder,
    bounds_m: tuple[float, float, float, float],
    lattice: Any | None,
    start: tuple[float, float] | None,
    target: tuple[float, float] | None,
) -> tuple[float, float, float, float]:
    """The part of the scene the flight used, plus two cells (whole scene if nothing flew)."""
    pts = list(rec.track_xy)
    pts += [tuple(s["target_scene"]) for s in rec.steps if s.get("target_scene")]
    pts += [p for p in (start, target) if p is not None]
    if not pts:
        return tuple(bounds_m)  # type: ignore[return-value]
    xy = np.asarray(pts, float)
    pad = 2.0 * (lattice.step_m if lattice is not None else 10.0)
    x0, y0 = xy.min(axis=0) - pad
    x1, y1 = xy.max(axis=0) + pad
    side = max(x1 - x0, y1 - y0)  # square, so cells stay square
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return (cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2)


def _near(a: float | None, b: float | None, tol: float) -> bool:
    return a is None and b is None or (a is not None and b is not None and abs(a - b) < tol)


def read_record(path: str | Path) -> list[dict[str, Any]]:
    """All rows of a ``flight.jsonl``."""
    with Path(path).open(encoding="utf-8") as f:
        return [json.loads(line) for line in f if line.strip()]


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if hasattr(value, "__dataclass_fields__"):
        return {k: getattr(value, k) for k in value.__dataclass_fields__}
    return str(value)
