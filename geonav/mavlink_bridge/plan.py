"""The flight's settings and plan: what is decided and checked before any connection.

:class:`FlightConfig` holds one flight's settings; :func:`plan_flight` checks them
against the scene and the policy (altitude, lattice, DSM obstacles, start and target
cells) and returns the :class:`FlightPlan` the phases fly. :func:`load_task` reads a
task file's task.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geonav.errors import CheckpointError, ConfigError
from geonav.mavlink_bridge.sequence import Timeouts

log = logging.getLogger(__name__)

Cell = tuple[int, int]


def validate_meta(meta: dict[str, Any], source: object = "policy") -> None:
    """Check the flight-relevant checkpoint meta: obs_size_px, alt_m (number or list), step_m.

    Raises:
        CheckpointError: a key is missing or has the wrong type.
    """
    missing = [k for k in ("obs_size_px", "alt_m", "step_m") if k not in meta]
    if missing:
        raise CheckpointError(f"checkpoint {source} meta lacks {missing}")
    alts = meta["alt_m"] if isinstance(meta["alt_m"], (list, tuple)) else [meta["alt_m"]]
    try:
        ok = bool(alts) and all(float(a) > 0 for a in alts) and float(meta["step_m"]) > 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise CheckpointError(
            f"checkpoint {source}: alt_m {meta['alt_m']!r} / step_m {meta['step_m']!r} "
            "must be positive numbers (alt_m may be a list of training altitudes)"
        )


def resolve_alt(meta: dict[str, Any], alt_m: float | None) -> float:
    """The flight altitude: ``alt_m`` if given, else the policy's single training altitude.

    Raises:
        ConfigError: the checkpoint was trained at several altitudes and none was chosen.
    """
    trained = meta.get("alt_m")
    alts = [float(a) for a in trained] if isinstance(trained, (list, tuple)) else None
    if alt_m is not None:
        if not (math.isfinite(alt_m) and alt_m > 0):
            raise ConfigError(f"flight altitude {alt_m!r} m: give a positive number of metres")
        if alts is not None and not any(abs(alt_m - a) < 1e-6 for a in alts):
            log.warning(
                "flying at %g m, which is not one of the policy's training altitudes %s",
                alt_m,
                alts,
            )
        return float(alt_m)
    if alts is not None:
        if len(alts) == 1:
            return alts[0]
        raise ConfigError(
            f"the policy was trained at several altitudes {alts} m: choose one with --alt"
        )
    return float(trained)  # type: ignore[arg-type]


@dataclass(frozen=True)
class FlightConfig:
    """Settings of one flight.

    Attributes:
        target_cell: lattice cell (ix east, iy north) to reach.
        start_cell: cell to start from (None: the cell under the take-off point).
        alt_m: flight altitude above the take-off point (None: the policy's ``alt_m``;
            required for a policy trained at several altitudes).
        step_m: lattice step (None: the policy's ``step_m``).
        region_m: lattice region (xmin, ymin, xmax, ymax) in scene metres
            (None: the scene bounds; cells count from its south-west corner).
        end: ``"land"`` or ``"rtl"`` at the end.
        camera: ``synthetic``, ``opencv:N`` or an rtsp:// URL.
        max_steps: step budget.
        arrive_tol_m: horizontal arrival tolerance.
        arrive_alt_tol_m: vertical arrival tolerance.
        arrive_speed_mps: arrival needs the speed below this too.
        step_timeout_s: seconds per step (None: 3 * step / 2 m/s + 10 s).
        pump_rate_hz: setpoint stream rate.
        policy_deadline_s: the pump stops and lands when the loop has not ticked for this long.
        heartbeat_timeout_s: autopilot heartbeat watchdog.
        position_timeout_s: LOCAL_POSITION_NED watchdog.
        fence_margin_m: setpoints stay this far inside the scene bounds (None: one
            lattice step); the measured position may overshoot the setpoint fence by
            half of it before the flight ends, so a breach is caught inside the scene.
        max_distance_m: fence radius around home (inf = off).
        max_alt_m: altitude clamp (upper); a clamp is logged as a warning.
        set_origin: send SET_GPS_GLOBAL_ORIGIN at the scene origin (GPS-less vehicles).
        telemetry_rate_hz: requested LOCAL_POSITION_NED rate.
        yaw_deg: fixed heading (0 = north, as the policy was trained).
        obstacles: the obstacle model (None: the environment's default
            ``geonav.tasks.ObstacleModel()``); cells blocked at the flight altitude
            are never flown into.
        on_obstacle: ``"stay"`` (refuse the move and keep position, as the env does)
            or ``"end"`` (end the flight with a safety stop).
        takeover_airborne: accept a vehicle that is already armed and flying; its
            current position and altitude are the start (otherwise geonav refuses).
        min_battery_pct: geonav refuses to arm below this battery charge, percent, and
            ends the flight with the end action when it falls below it in the air (above
            the autopilots' own critical levels: PX4 ``BAT_CRIT_THR`` 7 %, low 15 %);
            0 turns the check off.
        autopilot_fence: upload the scene's fence to the autopilot (fence items and its
            breach action = ``end``) before arming, and clear it after the landing;
            geonav's own fence stays the second layer.
        timeouts: per-phase timeouts.
    """

    target_cell: Cell
    start_cell: Cell | None = None
    alt_m: float | None = None
    step_m: float | None = None
    region_m: tuple[float, float, float, float] | None = None
    end: str = "land"
    camera: str = "synthetic"
    max_steps: int = 70
    arrive_tol_m: float = 0.5
    arrive_alt_tol_m: float = 1.0
    arrive_speed_mps: float = 0.3
    step_timeout_s: float | None = None
    pump_rate_hz: float = 15.0
    policy_deadline_s: float = 2.0
    heartbeat_timeout_s: float = 3.0
    position_timeout_s: float = 2.0
    fence_margin_m: float | None = None
    max_distance_m: float = math.inf
    max_alt_m: float = 120.0
    set_origin: bool = False
    telemetry_rate_hz: float = 10.0
    yaw_deg: float = 0.0
    obstacles: Any = None
    on_obstacle: str = "stay"
    takeover_airborne: bool = False
    min_battery_pct: float = 25.0
    autopilot_fence: bool = True
    timeouts: Timeouts = field(default_factory=Timeouts)

    def __post_init__(self) -> None:
        if self.end not in ("land", "rtl"):
            raise ConfigError(f"end action {self.end!r}: use 'land' or 'rtl'")
        if self.on_obstacle not in ("stay", "end"):
            raise ConfigError(f"on_obstacle {self.on_obstacle!r}: use 'stay' or 'end'")
        if self.fence_margin_m is not None and not self.fence_margin_m >= 0:
            raise ConfigError(f"fence margin {self.fence_margin_m!r} m must be >= 0")
        if not 0 <= self.min_battery_pct < 100:
            raise ConfigError(f"--min-battery {self.min_battery_pct!r} %: give 0..99 (0: off)")


@dataclass
class FlightPlan:
    """What is checked before connecting: altitude, lattice, obstacles, target (and start)."""

    alt_m: float
    step_m: float
    margin_m: float
    lattice: Any
    blocked: np.ndarray
    obstacles: Any
    notes: list[str]


def plan_flight(scene: Any, meta: dict[str, Any], cfg: FlightConfig,
                warn: bool = True) -> FlightPlan:
    """Check the flight plan against the scene before any connection.

    ``warn``: log the plan's notes (an altitude clamp) as warnings; a flight plans twice
    (before connecting, and at its start), and says each note once.

    Raises:
        ConfigError: no altitude chosen for a multi-altitude policy, or a start
            or target cell that is outside the lattice or an obstacle.
    """
    from geonav.tasks import Lattice, ObstacleModel, blocked_cells

    validate_meta(meta)
    notes: list[str] = []
    alt_m = resolve_alt(meta, cfg.alt_m)
    if alt_m > cfg.max_alt_m:
        note = f"altitude {alt_m:g} m clamped to {cfg.max_alt_m:g} m (--max-alt)"
        if warn:
            log.warning("%s", note)
        notes.append(note)
        alt_m = cfg.max_alt_m
    step_m = float(cfg.step_m if cfg.step_m is not None else meta["step_m"])
    margin = step_m if cfg.fence_margin_m is None else float(cfg.fence_margin_m)
    lattice = Lattice(cfg.region_m or tuple(scene.bounds_m), step_m)
    obstacles = cfg.obstacles if cfg.obstacles is not None else ObstacleModel()
    blocked = blocked_cells(scene, lattice, alt_m, obstacles)
    for name, c in (("target", cfg.target_cell), ("start", cfg.start_cell)):
        if c is None:
            continue
        if not lattice.contains(c):
            raise ConfigError(
                f"{name} cell {tuple(c)} is outside the lattice of shape {lattice.shape} "
                f"({step_m:g} m cells over region {tuple(round(v, 1) for v in lattice.region_m)})"
            )
        if blocked[tuple(c)]:
            raise ConfigError(
                f"{name} cell {tuple(c)} is an obstacle at {alt_m:g} m (the DSM rises above "
                f"{alt_m - obstacles.clearance_m:g} m there); choose another cell or altitude"
            )
    return FlightPlan(alt_m, step_m, margin, lattice, blocked, obstacles, notes)


def load_task(spec: str | Path) -> Any:
    """A task from ``FILE`` (a task set with one task) or ``FILE:NAME``.

    Raises:
        ConfigError: the file has several tasks and no name was given, or no such name.
    """
    from geonav.tasks import TaskSet

    text = str(spec)
    path, _, name = text.rpartition(":") if ":" in Path(text).name else (text, "", "")
    ts = TaskSet.load(path)
    if name:
        for task in ts.tasks:
            if task.name == name:
                return task
        raise ConfigError(f"task {name!r} not in {path}; it has {[t.name for t in ts.tasks]}")
    if len(ts.tasks) != 1:
        raise ConfigError(
            f"{path} holds {len(ts.tasks)} tasks: choose one with --task {path}:NAME "
            f"({', '.join(t.name for t in ts.tasks[:8])}{', ...' if len(ts.tasks) > 8 else ''})"
        )
    return ts.tasks[0]
