"""The flight loop: frame -> policy -> next lattice target -> arrival, on any vehicle.

This is the only module of the bridge that touches ``geonav.policy`` (lazily,
to load a checkpoint), so the backends never import torch. The loop talks to
a policy through :class:`Policy`: ``reset()``, ``act(image, target) -> int``
and a ``meta`` dict with ``obs_size_px``, ``alt_m``, ``step_m`` and
``fov_deg``.

Sequence (DESIGN.md "Deployment"): the plan (altitude, lattice, obstacles,
target) is checked before connecting; connect, heartbeat in STANDBY,
refuse a vehicle that is already armed or airborne (unless
``takeover_airborne``), telemetry requested, EKF origin and position known,
home inside the scene fence, take-off to the policy's altitude, fly to the
start cell, then per step get a frame, run the policy, send previous target
+ one lattice step (through lon/lat into the vehicle's own NED frame), wait
for arrival (distance AND speed under thresholds) while the measured
position stays inside the fence; a move into a cell the environment treats
as an obstacle (``geonav.tasks.blocked_cells``) is refused as in the env
(the vehicle stays) or ends the flight (``on_obstacle="end"``). Stop at the
target cell, the step budget or a safety rule; then LAND or RTL and wait
for disarm, in a ``finally`` (Ctrl-C, SIGTERM, SIGHUP and any exception
included). An operator takeover ends autonomy without any further command.
Every flight ends with an :data:`OUTCOMES` word and its exit code.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from geonav.errors import (
    CheckpointError,
    CommandRejected,
    ConfigError,
    FlightError,
    FlightTimeout,
    SafetyViolation,
)
from geonav.geo import LocalNED, ScenePoint
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.camera_source import (
    FrameSource,
    OpenCVFrames,
    SyntheticFrames,
    parse_camera,
)
from geonav.mavlink_bridge.conversion import ACTION_NAMES, ACTION_STEPS, TargetPlanner
from geonav.mavlink_bridge.pump import SetpointPump
from geonav.mavlink_bridge.record import FlightRecorder
from geonav.mavlink_bridge.safety import (
    Geofence,
    LinkLost,
    OperatorTakeover,
    PreflightRefused,
    Watchdog,
)
from geonav.mavlink_bridge.sequence import (
    Timeouts,
    end_flight,
    horizontal_distance_m,
    set_mode_confirmed,
    take_off,
    wait_position,
    wait_ready,
)
from geonav.mavlink_bridge.vehicle import Vehicle, VehicleState, open_vehicle

log = logging.getLogger(__name__)

Cell = tuple[int, int]
Progress = Callable[[str, float], None]

#: outcome -> process exit code (2 stays "bad input" for the CLI; signals give 128 + N).
OUTCOMES: dict[str, int] = {
    "reached": 0,
    "missed": 1,
    "refused": 3,
    "link_lost": 4,
    "takeover": 5,
    "safety_stop": 6,
    "interrupted": 130,
}
MIN_TAKEOVER_ALT_M = 1.0
"""--takeover-airborne refuses a vehicle lower than this above home (armed on the ground)."""
OUTCOME_WORDS = {
    "reached": "reached the target",
    "missed": "did not reach the target",
    "refused": "refused before arming",
    "link_lost": "link lost",
    "takeover": "operator took over",
    "safety_stop": "safety stop",
    "interrupted": "interrupted",
}


class Policy(Protocol):
    """What the flight loop needs from a policy."""

    meta: dict[str, Any]

    def reset(self) -> None:
        """Start of an episode (clears recurrent state)."""

    def act(self, image: np.ndarray, target: np.ndarray) -> int:
        """Action 0..3 for the current (N, N, 3) uint8 view and the target view."""


class ScriptedPolicy:
    """A policy that replays fixed actions (tests and dry runs of the flight machinery).

    Args:
        actions: the actions, in order; the last one repeats when they run out.
        meta: ``obs_size_px``, ``alt_m``, ``step_m``, ``fov_deg``.
        delay_s: sleep this long in every ``act`` (to emulate a slow or stalled policy).
    """

    def __init__(self, actions: Sequence[int], meta: dict[str, Any], delay_s: float = 0.0) -> None:
        self.actions = list(actions)
        self.meta = dict(meta)
        self.delay_s = delay_s
        self.calls = 0

    def reset(self) -> None:
        self.calls = 0

    def act(self, image: np.ndarray, target: np.ndarray) -> int:
        if image.shape != target.shape or image.dtype != np.uint8:
            raise FlightError(f"policy input {image.shape} {image.dtype} vs target {target.shape}")
        if self.delay_s:
            time.sleep(self.delay_s)
        a = self.actions[min(self.calls, len(self.actions) - 1)]
        self.calls += 1
        return int(a)


def path_actions(start: Cell, target: Cell) -> list[int]:
    """Actions of a shortest obstacle-free path on the lattice (east first, then north)."""
    dx, dy = target[0] - start[0], target[1] - start[1]
    return [1 if dx > 0 else 2] * abs(dx) + [0 if dy > 0 else 3] * abs(dy)


def load_policy(checkpoint: str | Path) -> Policy:
    """``geonav.policy.inference.PolicyRunner.from_checkpoint`` (imported lazily), validated.

    Raises:
        CheckpointError: the policy package or the checkpoint is unusable.
    """
    try:
        from geonav.policy.inference import PolicyRunner  # type: ignore[import-not-found]
    except ImportError as err:
        raise CheckpointError(
            f"cannot load {checkpoint}: geonav.policy.inference.PolicyRunner is not available "
            f"({err}); install geonav with its policy package"
        ) from err
    runner = PolicyRunner.from_checkpoint(checkpoint)
    validate_meta(runner.meta, checkpoint)
    return runner  # type: ignore[no-any-return]


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
    timeouts: Timeouts = field(default_factory=Timeouts)

    def __post_init__(self) -> None:
        if self.end not in ("land", "rtl"):
            raise ConfigError(f"end action {self.end!r}: use 'land' or 'rtl'")
        if self.on_obstacle not in ("stay", "end"):
            raise ConfigError(f"on_obstacle {self.on_obstacle!r}: use 'stay' or 'end'")
        if self.fence_margin_m is not None and not self.fence_margin_m >= 0:
            raise ConfigError(f"fence margin {self.fence_margin_m!r} m must be >= 0")


@dataclass
class FlightResult:
    """What happened.

    Attributes:
        success: the vehicle arrived at the target cell.
        reason: why the flight ended (target reached, step budget, the safety rule, the error).
        steps: policy steps flown.
        final_cell: last cell reached (None if autonomy never started).
        target_cell: the target.
        end_action: ``land``, ``rtl``, or ``none`` (operator takeover / never armed).
        disarmed: the vehicle was disarmed at the end.
        record_path: ``flight.jsonl``.
        png_path: ``track.png`` (None if plotting failed, or before :meth:`draw_track` when
            the flight was run with ``plot=False``).
        latencies_ms: frame -> setpoint latency per step.
        outcome: one of :data:`OUTCOMES` (``reached``, ``missed``, ``refused``,
            ``link_lost``, ``takeover``, ``safety_stop``, ``interrupted``).
        end_ok: the end action was confirmed and the vehicle disarmed (False when
            LAND/RTL failed or was never needed).
        signal_name: the signal that interrupted the flight (``SIGTERM``...), if any.
        notes: warnings the operator must see (altitude clamp, obstacle refusals).
    """

    success: bool
    reason: str
    steps: int
    final_cell: Cell | None
    target_cell: Cell
    end_action: str
    disarmed: bool
    record_path: Path
    png_path: Path | None
    latencies_ms: list[float] = field(default_factory=list)
    outcome: str = "missed"
    end_ok: bool = False
    signal_name: str | None = None
    notes: list[str] = field(default_factory=list)
    _draw: Callable[[], Path | None] | None = field(default=None, repr=False, compare=False)

    def draw_track(self) -> Path | None:
        """Draw ``track.png`` of a flight run with ``plot=False`` (once; later calls return
        the same path). None if plotting failed (logged)."""
        if self._draw is not None:
            self.png_path, self._draw = self._draw(), None
        return self.png_path

    @property
    def exit_code(self) -> int:
        """Process exit code of the outcome (128 + signal number when a signal ended it)."""
        return _exit_code(self.outcome, self.signal_name)

    def summary(self) -> str:
        """One line for the console."""
        if self.end_action == "none":
            end = (
                "no end action ("
                + ("the operator has control" if self.outcome == "takeover" else "nothing flown")
                + ")"
            )
        elif self.end_ok:
            end = f"end {self.end_action} confirmed, disarmed"
        elif self.outcome == "takeover":  # the operator changed the mode during the landing
            end = f"end {self.end_action} stopped by the operator (the operator has control)"
        else:
            end = f"end {self.end_action} NOT confirmed (disarmed {self.disarmed})"
            if "failsafe must act" not in self.reason:  # said once
                end += "; the autopilot's failsafe must act"
        words = OUTCOME_WORDS[self.outcome]
        # "operator took over: mode changed to 'hold' ...", not "operator took over:
        # operator takeover: mode changed ..." (PX4 SIH and ArduCopter SITL).
        reason = _strip_outcome(self.outcome, self.reason)
        head = reason if reason.lower().startswith(words) else f"{words}: {reason}"
        track = "" if self._draw is not None else f"; track {self.png_path}"
        return f"{head}; {self.steps} steps; {end}; record {self.record_path}{track}"


def _exit_code(outcome: str, signal_name: str | None) -> int:
    """The process exit code of an outcome: 128 + the signal's number when one ended it."""
    if outcome == "interrupted" and signal_name:
        return 128 + int(signal.Signals[signal_name])
    return OUTCOMES[outcome]


#: How errors of an outcome begin their message ("link lost: no autopilot heartbeat").
_OUTCOME_PREFIXES = {
    "link_lost": ("link lost: ",),
    "takeover": ("operator took over: ", "operator takeover: "),
    "interrupted": ("interrupted: ",),
}


def _strip_outcome(outcome: str, text: str) -> str:
    """``text`` without a leading restatement of ``outcome`` (the summary says it once)."""
    for prefix in (OUTCOME_WORDS[outcome] + ": ",) + _OUTCOME_PREFIXES.get(outcome, ()):
        if text.lower().startswith(prefix):
            return text[len(prefix):]
    return text


class FlightInterrupted(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP during a flight (handled like Ctrl-C: land, record)."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(signal.Signals(signum).name)


class _StopSignals:
    """Turns the first SIGINT/SIGTERM/SIGHUP into :class:`FlightInterrupted`; later ones are logged.

    Installed only in the main thread; a SIGINT that is ignored (a background
    job) stays ignored, SIGTERM and SIGHUP still land the vehicle.
    """

    SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")

    def __init__(self) -> None:
        self.received: int | None = None
        self.may_raise = True
        self._old: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for name in self.SIGNALS:
            sig = getattr(signal, name, None)
            if sig is None:
                continue
            old = signal.getsignal(sig)
            if sig == signal.SIGINT and old is signal.SIG_IGN:
                continue
            self._old[sig] = old
            signal.signal(sig, self._handle)

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.received is None:
            self.received = signum
            log.error("%s received: ending the flight (LAND/RTL as configured)", name)
            if self.may_raise:
                raise FlightInterrupted(signum)
            return
        log.warning("%s received again: geonav is already ending the flight", name)


@contextmanager
def stop_signals() -> Iterator[_StopSignals]:
    """SIGINT/SIGTERM/SIGHUP end the flight like Ctrl-C while the block runs."""
    sigs = _StopSignals()
    sigs.install()
    try:
        yield sigs
    finally:
        sigs.restore()


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


def run_flight(
    vehicle: Vehicle,
    scene: Any,
    policy: Policy,
    cfg: FlightConfig,
    out_dir: str | Path,
    progress: Progress | None = None,
    frames: FrameSource | None = None,
    *,
    plot: bool = True,
    warn: bool = True,
) -> FlightResult:
    """Fly ``policy`` on ``vehicle`` over ``scene`` (a :class:`geonav.scene.Scene`).

    Never raises for flight problems: they end the flight safely and are
    reported in the result (``outcome`` and ``exit_code``). SIGINT, SIGTERM and
    SIGHUP (when called from the main thread) end the flight like Ctrl-C.

    Args:
        plot: draw ``track.png`` before returning; False returns as soon as the flight
            has ended and its record is written (the result's :meth:`FlightResult.draw_track`
            draws it), so a command can say the outcome first.
        warn: log the plan's notes (an altitude clamp) as warnings (:func:`fly` has).

    Raises:
        ConfigError: the plan is invalid (checked before connecting).
    """
    with stop_signals() as sigs:
        result = _run_flight(vehicle, scene, policy, cfg, out_dir, progress, frames, sigs,
                             warn)
    if plot:
        result.draw_track()
    return result


def _run_flight(
    vehicle: Vehicle,
    scene: Any,
    policy: Policy,
    cfg: FlightConfig,
    out_dir: str | Path,
    progress: Progress | None,
    frames: FrameSource | None,
    sigs: _StopSignals,
    warn: bool = True,
) -> FlightResult:
    from geonav.camera import Camera, WarpRenderer

    plan = plan_flight(scene, policy.meta, cfg, warn=warn)
    t = cfg.timeouts
    meta = policy.meta
    alt_m, step_m, lattice = plan.alt_m, plan.step_m, plan.lattice
    size_px = int(meta.get("obs_size_px", 84))
    camera = Camera(size_px=size_px, fov_deg=float(meta.get("fov_deg", 90.0)))
    rec = FlightRecorder(out_dir)
    report = progress or (lambda phase, frac: None)
    pump: SetpointPump | None = None
    watchdog: Watchdog | None = None
    planner: TargetPlanner | None = None
    fence: Geofence | None = None
    cell: Cell | None = None
    start_xy: tuple[float, float] | None = None
    target_xy: tuple[float, float] | None = None
    success = False
    reason = ""
    outcome = "missed"
    steps = 0
    latencies: list[float] = []
    notes = list(plan.notes)
    phase = "preflight"
    we_fly = False  # geonav armed the vehicle (or took an airborne one over)
    last_sample = [0.0]
    rec.write(
        "header",
        scene=scene.name,
        bounds_m=scene.bounds_m,
        scene_origin=scene.origin,
        config=asdict(cfg),
        policy_meta=meta,
        alt_m=alt_m,
        step_m=step_m,
        fence_margin_m=plan.margin_m,
        lattice_region_m=lattice.region_m,
        blocked_cells=[list(map(int, c)) for c in np.argwhere(plan.blocked)],
    )
    for note in notes:
        rec.event(note)

    def sample(s: VehicleState, phase_name: str | None = None) -> None:
        """Record the measured track (every phase: climb, steps, return, landing)."""
        now = time.monotonic()
        if planner is None or s.position is None or now - last_sample[0] < 0.1:
            return
        last_sample[0] = now
        p, alt = planner.to_scene(s.position)
        rec.sample(p.x_m, p.y_m, phase_name or phase, alt)

    def fence_check_position(s: VehicleState) -> None:
        if fence is None or planner is None or s.position is None:
            return
        p, _ = planner.to_scene(s.position)
        why = fence.position_violation(p)
        if why is not None:
            raise SafetyViolation(f"position fence: {why}")

    try:
        report("connect", 0.0)
        vehicle.connect(t.connect_s)
        rec.event(f"connected: {vehicle.autopilot}")
        s = wait_ready(vehicle, t)
        if s.armed and not cfg.takeover_airborne:
            raise PreflightRefused(
                f"the vehicle is already armed (mode {s.mode}): geonav does not take over a "
                "vehicle someone else is flying; disarm it, or pass --takeover-airborne to "
                "start from its current position and altitude"
            )
        vehicle.request_telemetry(cfg.telemetry_rate_hz, t.command_s)
        s = wait_position(vehicle, t, set_origin=scene.origin if cfg.set_origin else None)
        assert s.origin is not None and s.position is not None
        airborne = s.armed or s.landed_state in (
            M.MAV_LANDED_STATE_IN_AIR,
            M.MAV_LANDED_STATE_TAKEOFF,
            M.MAV_LANDED_STATE_LANDING,
        )
        if airborne and not cfg.takeover_airborne:
            raise PreflightRefused(
                f"the vehicle is already in the air (landed state {s.landed_state}, mode "
                f"{s.mode}): pass --takeover-airborne to start from its current position"
            )
        if cfg.takeover_airborne and not (s.armed and airborne):
            raise PreflightRefused(
                "--takeover-airborne given but the vehicle is not armed and flying "
                f"(armed {s.armed}, landed state {s.landed_state}); fly without it"
            )
        rec.event(f"EKF origin {s.origin}; position NED {s.position}")
        report("connect", 1.0)
        home_down = s.position.down_m
        if airborne:
            # The take-off point is home; the EKF origin is usually there too.
            home_down = s.origin.alt_m - s.home.alt_m if s.home is not None else 0.0
            alt_m = float(home_down - s.position.down_m)
            if alt_m < MIN_TAKEOVER_ALT_M:
                raise PreflightRefused(
                    f"the vehicle is armed but on the ground ({alt_m:.1f} m above home): "
                    "--takeover-airborne takes over a vehicle in the air; disarm it, or fly "
                    f"it above {MIN_TAKEOVER_ALT_M:g} m first")
            rec.event(f"taking over an airborne vehicle at {alt_m:.1f} m above home")
            try:
                plan = plan_flight(scene, meta, replace(cfg, alt_m=alt_m, start_cell=None))
            except ConfigError as err:
                raise PreflightRefused(f"taking over at {alt_m:.1f} m: {err}") from err
        planner = TargetPlanner(
            scene.frame, s.origin, home_down, alt_m, cfg.yaw_deg, autopilot=vehicle.autopilot
        )
        here_scene, _ = planner.to_scene(s.position)
        fence = Geofence.from_bounds(
            scene.bounds_m,
            plan.margin_m,
            home=here_scene,
            max_distance_m=cfg.max_distance_m,
            max_alt_m=cfg.max_alt_m,
            overshoot_m=plan.margin_m / 2.0,
        )
        why = fence.violation(here_scene)
        if why is not None:
            raise PreflightRefused(f"the vehicle is outside the scene fence: {why}")
        if not fence.min_alt_m <= alt_m <= fence.max_alt_m:
            raise PreflightRefused(
                f"flight altitude {alt_m:.1f} m is outside the fence's {fence.min_alt_m:g}.."
                f"{fence.max_alt_m:g} m band"
            )
        start_cell = (cfg.start_cell if not airborne else None) or lattice.cell_of(here_scene)
        if not lattice.contains(start_cell) or plan.blocked[start_cell]:
            raise PreflightRefused(
                f"start cell {start_cell} is outside the lattice {lattice.shape} or an obstacle "
                f"at {alt_m:g} m"
            )
        here_cell = lattice.cell_of(here_scene)
        if lattice.contains(here_cell) and plan.blocked[here_cell]:
            raise PreflightRefused(
                f"the take-off point's cell {here_cell} is an obstacle at {alt_m:g} m: "
                "the climb would hit it"
            )
        start_pt = lattice.center(start_cell)
        target_pt = lattice.center(cfg.target_cell)
        start_xy, target_xy = (start_pt.x_m, start_pt.y_m), (target_pt.x_m, target_pt.y_m)
        for name, pt in (("start", start_pt), ("target", target_pt)):
            why = fence.violation(pt)
            if why is not None:
                raise PreflightRefused(
                    f"{name} cell is outside the geofence ({why}); fence margin "
                    f"{plan.margin_m:g} m (--fence-margin)"
                )

        renderer = WarpRenderer(scene, camera)
        target_img = renderer.render(target_pt.x_m, target_pt.y_m, alt_m, cfg.yaw_deg)
        check = getattr(policy, "check_outputs", None)
        if check is not None:  # a policy that cannot act is refused before anything arms
            try:
                check(renderer.render(start_pt.x_m, start_pt.y_m, alt_m, cfg.yaw_deg),
                      target_img)
            except CheckpointError as err:
                raise PreflightRefused(str(err)) from err
        if frames is None:
            kind, dev = parse_camera(cfg.camera)
            frames = (
                SyntheticFrames(renderer, planner.to_scene, cfg.yaw_deg)
                if kind == "synthetic"
                else OpenCVFrames(dev if dev is not None else 0, size_px)
            )

        watchdog = Watchdog(
            cfg.heartbeat_timeout_s, cfg.position_timeout_s, M.AUTONOMY_MODE[vehicle.autopilot]
        )

        def fence_check(ned: LocalNED) -> None:
            assert planner is not None and fence is not None
            p, alt = planner.to_scene(ned)
            fence.check(p)
            if not (fence.min_alt_m - 0.5 <= alt <= fence.max_alt_m + 0.5):
                raise SafetyViolation(f"setpoint altitude {alt:.1f} m outside the altitude band")

        pump = SetpointPump(
            vehicle,
            rate_hz=cfg.pump_rate_hz,
            deadline_s=cfg.policy_deadline_s,
            fence_check=fence_check,
            watchdog=watchdog,
            land_timeout_s=t.command_s,
        )

        def in_flight_check() -> None:
            st = vehicle.state()
            sample(st)
            fence_check_position(st)

        report("take-off", 0.0)
        if airborne:
            phase = "takeover"
            we_fly = True
            hold = planner.to_ned(here_scene)
            pump.set_target(LocalNED(s.position.north_m, s.position.east_m, hold.down_m), 0.0)
            pump.start()
            if vehicle.autopilot == M.PX4:
                time.sleep(min(1.2, t.mode_s / 2))
            set_mode_confirmed(vehicle, watchdog.autonomy_mode, t, pump.tick, watchdog)
        else:
            phase = "arming"

            def armed() -> None:
                nonlocal phase, we_fly
                phase, we_fly = "takeoff", True

            take_off(
                vehicle,
                pump,
                planner.to_ned(here_scene),
                cfg.yaw_deg,
                cfg.arrive_alt_tol_m,
                t,
                watchdog=watchdog,
                check=in_flight_check,
                on_armed=armed,
            )
        phase = "autonomy"
        watchdog.engage()
        rec.event(f"airborne at {alt_m:.1f} m in {vehicle.state().mode}")
        report("take-off", 1.0)

        step_timeout = cfg.step_timeout_s or (3.0 * step_m / 2.0 + 10.0)

        def arrive(ned: LocalNED, timeout_s: float) -> tuple[float, LocalNED]:
            assert pump is not None and watchdog is not None
            return _wait_arrival(vehicle, pump, watchdog, ned, cfg, timeout_s, in_flight_check)

        # Fly to the start cell (a positioning leg, not a policy step).
        previous = start_pt
        ned = planner.to_ned(start_pt)
        pump.set_target(ned, cfg.yaw_deg)
        arrive(ned, step_timeout + horizontal_distance_m(ned, vehicle.state().position or ned) / 2)
        cell = start_cell
        rec.event(f"at start cell {cell}")
        policy.reset()
        while True:
            if cell == cfg.target_cell:
                success, reason = True, f"target cell {cfg.target_cell} reached in {steps} steps"
                outcome = "reached"
                break
            if steps >= cfg.max_steps:
                reason = f"step budget of {cfg.max_steps} spent at cell {cell}"
                outcome = "missed"
                break
            pump.raise_if_fault()
            state = vehicle.state()
            watchdog.check(state)
            fence_check_position(state)
            t_frame = time.perf_counter()
            image = frames.frame(state)
            action = int(policy.act(image, target_img))
            pump.tick()
            pump.raise_if_fault()
            # A step counts once it is done and recorded: one cut short by a link loss or
            # an error is not "flown" (the summary said "3 steps" with 2 done).
            n = steps + 1
            if action not in ACTION_STEPS:
                raise FlightError(f"policy returned action {action}; expected 0..3")
            nxt = planner.next_target(previous, action, step_m)
            nxt_cell = lattice.cell_of(nxt)
            base = dict(step=n, action=action, action_name=ACTION_NAMES[action])
            if not lattice.contains(nxt_cell):
                # As in the environment: a move out of the region leaves the agent in place.
                rec.write(
                    "step",
                    **base,
                    cell=cell,
                    blocked=True,
                    events=["move out of the lattice: stayed"],
                )
                steps = n
                report("steps", steps / cfg.max_steps)
                continue
            if plan.blocked[nxt_cell]:
                text = (
                    f"obstacle: cell {nxt_cell} is blocked at {alt_m:g} m (DSM, "
                    f"env rule geonav.tasks.blocked_cells)"
                )
                if cfg.on_obstacle == "end":
                    rec.write(
                        "step",
                        **base,
                        cell=cell,
                        blocked=True,
                        events=[f"{text}: flight ended (--on-obstacle end)"],
                    )
                    steps = n  # the step is done: it ended the flight where it stands
                    raise SafetyViolation(f"{text}; --on-obstacle end")
                rec.write(
                    "step",
                    **base,
                    cell=cell,
                    blocked=True,
                    events=[f"{text}: refused, kept position (--on-obstacle stay)"],
                )
                steps = n
                report("steps", steps / cfg.max_steps)
                log.warning("%s: move refused, vehicle keeps its position", text)
                continue
            ned = planner.to_ned(nxt)
            try:
                pump.set_target(ned, cfg.yaw_deg)
            except SafetyViolation as err:
                rec.write(
                    "step",
                    **base,
                    cell=cell,
                    target_scene=None,
                    refused_target=(nxt.x_m, nxt.y_m),
                    events=[f"geofence: {err}"],
                )
                steps = n  # recorded: it ended the flight where it stands
                raise
            latency_ms = (time.perf_counter() - t_frame) * 1000.0
            latencies.append(latency_ms)
            arrival_s, measured = arrive(ned, step_timeout)
            m_scene, m_alt = planner.to_scene(measured)
            previous, cell = nxt, nxt_cell
            rec.write(
                "step",
                **base,
                cell=cell,
                target_scene=(nxt.x_m, nxt.y_m),
                target_ned=(ned.north_m, ned.east_m, ned.down_m),
                measured_ned=(measured.north_m, measured.east_m, measured.down_m),
                measured_scene=(m_scene.x_m, m_scene.y_m),
                measured_alt_m=m_alt,
                arrival_s=round(arrival_s, 3),
                latency_ms=round(latency_ms, 3),
                events=[],
            )
            steps = n
            report("steps", steps / cfg.max_steps)
    except FlightInterrupted as err:
        reason = f"interrupted by {err.args[0]}"
        outcome = "interrupted"
        rec.event(reason)
    except KeyboardInterrupt:
        reason = "interrupted by the operator (Ctrl-C)"
        outcome = "interrupted"
        sigs.received = sigs.received or signal.SIGINT
        log.error("%s", reason)
        rec.event(reason)
    except FlightError as err:
        outcome = _classify(err, phase)
        reason = (
            str(err)
            if isinstance(err, SafetyViolation | LinkLost | PreflightRefused)
            else (f"{type(err).__name__}: {err}")
        )
        log.error("flight ended (%s): %s", outcome, reason)
        rec.event(f"{outcome}: {reason}")
    except Exception as err:  # any bug still ends in LAND/RTL below
        reason = f"unexpected error: {type(err).__name__}: {err}"
        outcome = "safety_stop"
        log.exception("flight ended by an unexpected error")
        rec.event(reason)
    finally:
        sigs.may_raise = False  # the landing itself is never interrupted by a signal
        end_action, disarmed, end_ok, end_outcome, end_note = _finish(
            vehicle,
            pump,
            watchdog,
            cfg,
            outcome == "takeover",
            we_fly,
            rec,
            lambda st: sample(st, "landing"),
        )
        if frames is not None:
            frames.close()
    if end_outcome is not None and outcome in ("reached", "missed", "safety_stop"):
        outcome = end_outcome
    if end_note:
        if reason and end_outcome is not None:
            # The outcome words head the summary once: "link lost: <why the flight
            # ended>; no autopilot heartbeat ...", not "...; link lost: no ..." (PX4 SIH).
            end_note = _strip_outcome(end_outcome, end_note)
        reason = f"{reason}; {end_note}" if reason else end_note
    signal_name = None
    if sigs.received is not None:
        signal_name = signal.Signals(sigs.received).name
        if outcome != "interrupted":
            rec.event(f"{signal_name} received while ending the flight")
    rec.write(
        "result",
        success=success,
        outcome=outcome,
        exit_code=_exit_code(outcome, signal_name),  # 143 for SIGTERM, as the process exits
        reason=reason,
        steps=steps,
        final_cell=cell,
        end_action=end_action,
        end_ok=end_ok,
        disarmed=disarmed,
        signal=signal_name,
        notes=notes,
    )
    rec.close()
    try:
        vehicle.close()
    except Exception as err:  # noqa: BLE001 - closing never ends in a traceback
        log.debug("closing vehicle: %s", err)
    report("done", 1.0)

    def draw() -> Path | None:
        # After the result is recorded and returned: drawing waits for nothing the
        # flight decides (matplotlib on a loaded machine took 30-70 s).
        try:
            return rec.plot(scene, lattice, start_xy, target_xy, fence)
        except (OSError, ValueError) as err:
            log.warning("track plot failed: %s", err)
            return None

    return FlightResult(
        success,
        reason,
        steps,
        cell,
        cfg.target_cell,
        end_action,
        disarmed,
        rec.path,
        None,
        latencies,
        outcome=outcome,
        end_ok=end_ok,
        signal_name=signal_name if outcome == "interrupted" else None,
        notes=notes,
        _draw=draw,
    )


def _classify(err: FlightError, phase: str) -> str:
    """Outcome word of a flight error raised in ``phase``."""
    if isinstance(err, LinkLost):
        return "link_lost"
    if isinstance(err, OperatorTakeover):
        return "takeover"
    if isinstance(err, PreflightRefused):
        return "refused"
    if phase in ("preflight", "arming") and isinstance(err, (CommandRejected, FlightTimeout)):
        return "refused"
    if phase in ("preflight", "arming") and not isinstance(err, SafetyViolation):
        return "refused"
    return "safety_stop"


def _wait_arrival(
    vehicle: Vehicle,
    pump: SetpointPump,
    watchdog: Watchdog,
    target: LocalNED,
    cfg: FlightConfig,
    timeout_s: float,
    check: Callable[[], None],
) -> tuple[float, LocalNED]:
    """Wait until LOCAL_POSITION_NED is within tolerance of ``target`` AND slow.

    ``check`` runs every cycle (track sample and the position fence).

    Returns:
        (seconds it took, the measured position).
    """
    t0 = time.monotonic()
    while True:
        pump.tick()
        pump.raise_if_fault()
        s = vehicle.state()
        watchdog.check(s)
        check()
        now = time.monotonic()
        if s.position is not None:
            d_h = horizontal_distance_m(s.position, target)
            d_v = abs(s.position.down_m - target.down_m)
            if (
                d_h <= cfg.arrive_tol_m
                and d_v <= cfg.arrive_alt_tol_m
                and s.speed_mps <= cfg.arrive_speed_mps
            ):
                return now - t0, s.position
        if now - t0 > timeout_s:
            raise FlightTimeout(
                f"not arrived at NED ({target.north_m:.1f}, {target.east_m:.1f}, "
                f"{target.down_m:.1f}) within {timeout_s:.1f} s (last position {s.position}, "
                f"speed {s.speed_mps:.2f} m/s)"
            )
        time.sleep(0.02)


def _finish(
    vehicle: Vehicle,
    pump: SetpointPump | None,
    watchdog: Watchdog | None,
    cfg: FlightConfig,
    takeover: bool,
    we_fly: bool,
    rec: FlightRecorder,
    sample: Callable[[VehicleState], None],
) -> tuple[str, bool, bool, str | None, str]:
    """Stop the stream, then LAND/RTL confirmed on the heartbeat and wait for disarm.

    Nothing is commanded after a takeover, or on a vehicle geonav never armed.

    Returns:
        (end action, disarmed, end confirmed, outcome override or None, note for the reason).
    """
    if pump is not None:
        pump.stop()
    try:
        s = vehicle.state()
    except FlightError:
        return "none", False, False, None, ""
    if takeover:
        rec.event("operator has control: no further commands from geonav")
        log.warning("someone else has control (mode %s); geonav sends nothing more", s.mode)
        return "none", not s.armed, False, None, ""
    if not we_fly:
        return "none", not s.armed, False, None, ""
    try:
        s = end_flight(vehicle, cfg.end, cfg.timeouts, watchdog, sample)
        rec.event(f"{cfg.end} confirmed on the heartbeat, disarmed")
        return cfg.end, not s.armed, True, None, ""
    except OperatorTakeover as err:
        log.warning("%s", err)
        rec.event(str(err))
        return cfg.end, False, False, "takeover", str(err)
    except LinkLost as err:
        log.error("%s", err)
        rec.event(f"{cfg.end} failed: {err}")
        return cfg.end, False, False, "link_lost", str(err)
    except FlightError as err:
        note = f"{cfg.end.upper()} failed: {err}; the autopilot's own failsafe must act"
        log.error("%s", note)
        rec.event(note)
        try:
            return cfg.end, not vehicle.state().armed, False, None, note
        except FlightError:
            return cfg.end, False, False, None, note


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


def fly(
    policy: Policy | str | Path,
    scene: Any,
    *,
    target_cell: Cell | None = None,
    task: Any = None,
    connect: str | None = None,
    backend: str = "pymavlink",
    camera: str = "synthetic",
    start_cell: Cell | None = None,
    end: str = "land",
    dry_run: bool = False,
    autopilot: str = "px4",
    out_dir: str | Path = "flight",
    emulator_config: Any = None,
    progress: Progress | None = None,
    plot: bool = True,
    **config: Any,
) -> FlightResult:
    """Fly a checkpoint (or a Policy) on a scene; with ``dry_run`` against an in-process emulator.

    The plan (altitude, lattice, obstacles, start and target cells) is checked
    before any connection is opened.

    Args:
        policy: a checkpoint path or an object following :class:`Policy`.
        scene: a :class:`geonav.scene.Scene` or a scene package folder.
        target_cell: lattice cell to reach (in the task's lattice when ``task`` is given).
        task: a :class:`geonav.tasks.NavTask` (or ``FILE[:NAME]``): its region, step,
            altitude, target, step budget and obstacle model (``target_cell`` and
            ``config`` override them).
        connect: connection string (ignored with ``dry_run``).
        backend: ``pymavlink`` or ``mavsdk``.
        camera: ``synthetic``, ``opencv:N`` or rtsp URL.
        start_cell: start cell (None: under the take-off point).
        end: ``land`` or ``rtl``.
        dry_run: start a :class:`~geonav.mavlink_bridge.emulator.Emulator` with home at the
            start cell and fly against it.
        autopilot: emulator flavour for ``dry_run``.
        out_dir: folder for the flight record.
        emulator_config: an EmulatorConfig to use for ``dry_run`` (home is set from the scene).
        progress: callback (phase, fraction).
        plot: draw ``track.png`` before returning (False: the result's
            :meth:`FlightResult.draw_track` draws it, so the outcome can be said first).
        **config: further :class:`FlightConfig` fields.

    Raises:
        ConfigError: a bad plan or option (before connecting).
    """
    from geonav.scene import Scene

    if not isinstance(scene, Scene):
        scene = Scene.open(scene)
    if isinstance(task, (str, Path)):
        task = load_task(task)
    if task is not None:
        for key, value in (
            ("region_m", tuple(task.region_m)),
            ("step_m", task.step_m),
            ("alt_m", task.alt_m),
            ("max_steps", task.max_steps),
            ("obstacles", task.obstacles),
        ):
            if config.get(key) is None:
                config[key] = value
        if target_cell is None:
            target_cell = tuple(task.target_cell)
    if target_cell is None:
        raise ConfigError("no target: give --target IX,IY or --task FILE[:NAME]")
    config = {k: v for k, v in config.items() if v is not None}
    cfg = FlightConfig(
        target_cell=(int(target_cell[0]), int(target_cell[1])),
        start_cell=None if start_cell is None else (int(start_cell[0]), int(start_cell[1])),
        end=end,
        camera=camera,
        **config,
    )
    pol: Policy = load_policy(policy) if isinstance(policy, (str, Path)) else policy
    plan = plan_flight(scene, pol.meta, cfg)  # before connecting: bad plans fail fast
    emu = None
    if dry_run:
        from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig

        if cfg.start_cell is None:
            nx, ny = plan.lattice.shape
            free = [(ix, iy) for ix in range(nx) for iy in range(ny) if not plan.blocked[ix, iy]]
            centre = (nx // 2, ny // 2)
            cfg = replace(
                cfg,
                start_cell=min(free, key=lambda c: abs(c[0] - centre[0]) + abs(c[1] - centre[1])),
            )
        assert cfg.start_cell is not None
        home = scene.frame.to_lonlat(plan.lattice.center(cfg.start_cell), 0.0)
        # A dry run is a rehearsal at 3x emulated speed; the emulator bounds its emulated
        # time per iteration, so a busy machine slows the vehicle instead of jumping it.
        ec = emulator_config or EmulatorConfig(
            autopilot=autopilot,
            time_scale=3.0,
            boot_s=1.0,
            prearm_s=2.0,
            origin_s=1.0,
            local_position_s=1.5,
        )
        ec.home = home
        ec.autopilot = autopilot if emulator_config is None else ec.autopilot
        emu = Emulator(ec).start()
        connect = emu.connect_url
    if connect is None:
        raise ConfigError("no connection: give --connect URL or --dry-run")
    try:
        vehicle = open_vehicle(connect, backend)
        return run_flight(vehicle, scene, pol, cfg, out_dir, progress, plot=plot, warn=False)
    finally:
        if emu is not None:
            emu.stop()


__all__ = [
    "OUTCOMES",
    "FlightConfig",
    "FlightInterrupted",
    "FlightResult",
    "Policy",
    "ScenePoint",
    "ScriptedPolicy",
    "fly",
    "load_policy",
    "load_task",
    "path_actions",
    "plan_flight",
    "resolve_alt",
    "run_flight",
    "stop_signals",
]
