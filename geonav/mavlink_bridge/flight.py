"""The flight loop: frame -> policy -> next lattice target -> arrival, on any vehicle.

This is the only module of the bridge that touches ``geonav.policy`` (lazily,
to load a checkpoint), so the backends never import torch. The loop talks to
a policy through :class:`Policy`: ``reset()``, ``act(image, target) -> int``
and a ``meta`` dict with ``obs_size_px``, ``alt_m``, ``step_m`` and
``fov_deg``.

Sequence (DESIGN.md "Deployment"): connect, heartbeat in STANDBY, telemetry
requested, EKF origin and position known, home inside the scene fence,
take-off to the policy's altitude, fly to the start cell, then per step get
a frame, run the policy, send previous target + one lattice step (through
lon/lat into the vehicle's NED), wait for arrival (distance AND speed under
thresholds); stop at the target cell, the step budget or a safety rule; then
LAND or RTL and wait for disarm, in a ``finally`` (Ctrl-C and any exception
included). An operator takeover ends autonomy without any further command.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from geonav.errors import CheckpointError, ConfigError, FlightError, FlightTimeout, SafetyViolation
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
from geonav.mavlink_bridge.safety import TAKEOVER, Geofence, Watchdog
from geonav.mavlink_bridge.sequence import (
    Timeouts,
    end_flight,
    horizontal_distance_m,
    take_off,
    wait_position,
    wait_ready,
)
from geonav.mavlink_bridge.vehicle import Vehicle, VehicleState, open_vehicle

log = logging.getLogger(__name__)

Cell = tuple[int, int]
Progress = Callable[[str, float], None]


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
    """``geonav.policy.inference.PolicyRunner.from_checkpoint`` (imported lazily).

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
    missing = [k for k in ("obs_size_px", "alt_m", "step_m") if k not in runner.meta]
    if missing:
        raise CheckpointError(f"checkpoint {checkpoint} meta lacks {missing}")
    return runner  # type: ignore[no-any-return]


@dataclass(frozen=True)
class FlightConfig:
    """Settings of one flight.

    Attributes:
        target_cell: lattice cell (ix east, iy north) to reach.
        start_cell: cell to start from (None: the cell under the take-off point).
        alt_m: flight altitude above the take-off point (None: the policy's ``alt_m``).
        step_m: lattice step (None: the policy's ``step_m``).
        region_m: lattice region (xmin, ymin, xmax, ymax) in scene metres
            (None: the scene bounds shrunk by ``fence_margin_m``).
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
        fence_margin_m: fence = scene bounds shrunk by this.
        max_distance_m: fence radius around home (inf = off).
        max_alt_m: altitude clamp (upper).
        set_origin: send SET_GPS_GLOBAL_ORIGIN at the scene origin (GPS-less vehicles).
        telemetry_rate_hz: requested LOCAL_POSITION_NED rate.
        yaw_deg: fixed heading (0 = north, as the policy was trained).
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
    fence_margin_m: float = 0.0
    max_distance_m: float = math.inf
    max_alt_m: float = 120.0
    set_origin: bool = False
    telemetry_rate_hz: float = 10.0
    yaw_deg: float = 0.0
    timeouts: Timeouts = field(default_factory=Timeouts)

    def __post_init__(self) -> None:
        if self.end not in ("land", "rtl"):
            raise ConfigError(f"end action {self.end!r}: use 'land' or 'rtl'")


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
        png_path: ``track.png`` (None if plotting failed).
        latencies_ms: frame -> setpoint latency per step.
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


def run_flight(
    vehicle: Vehicle,
    scene: Any,
    policy: Policy,
    cfg: FlightConfig,
    out_dir: str | Path,
    progress: Progress | None = None,
    frames: FrameSource | None = None,
) -> FlightResult:
    """Fly ``policy`` on ``vehicle`` over ``scene`` (a :class:`geonav.scene.Scene`).

    Never raises for flight problems: they end the flight safely and are
    reported in the result (KeyboardInterrupt is re-raised after landing).
    """
    from geonav.camera import Camera, WarpRenderer
    from geonav.tasks import Lattice

    t = cfg.timeouts
    meta = policy.meta
    alt_m = float(cfg.alt_m if cfg.alt_m is not None else meta["alt_m"])
    step_m = float(cfg.step_m if cfg.step_m is not None else meta["step_m"])
    size_px = int(meta.get("obs_size_px", 84))
    camera = Camera(size_px=size_px, fov_deg=float(meta.get("fov_deg", 90.0)))
    rec = FlightRecorder(out_dir)
    report = progress or (lambda phase, frac: None)
    pump: SetpointPump | None = None
    lattice = None
    fence: Geofence | None = None
    cell: Cell | None = None
    start_xy: tuple[float, float] | None = None
    target_xy: tuple[float, float] | None = None
    success = False
    reason = ""
    steps = 0
    latencies: list[float] = []
    takeover = False
    armed_once = False
    interrupted: BaseException | None = None
    rec.write(
        "header",
        scene=scene.name,
        bounds_m=scene.bounds_m,
        scene_origin=scene.origin,
        config=asdict(cfg),
        policy_meta=meta,
        alt_m=alt_m,
        step_m=step_m,
    )
    try:
        report("connect", 0.0)
        vehicle.connect(t.connect_s)
        rec.event(f"connected: {vehicle.autopilot}")
        wait_ready(vehicle, t)
        vehicle.request_telemetry(cfg.telemetry_rate_hz, t.command_s)
        s = wait_position(vehicle, t, set_origin=scene.origin if cfg.set_origin else None)
        assert s.origin is not None and s.position is not None
        rec.event(f"EKF origin {s.origin}; home position NED {s.position}")
        report("connect", 1.0)
        planner = TargetPlanner(scene.frame, s.origin, s.position.down_m, alt_m, cfg.yaw_deg)
        home_scene, _ = planner.to_scene(s.position)
        fence = Geofence.from_bounds(
            scene.bounds_m,
            cfg.fence_margin_m,
            home=home_scene,
            max_distance_m=cfg.max_distance_m,
            max_alt_m=cfg.max_alt_m,
        )
        fence.check(home_scene)
        clamped = fence.clamp_alt(alt_m)
        if clamped != alt_m:
            rec.event(f"altitude {alt_m} m clamped to {clamped} m")
            planner.alt_m = alt_m = clamped
        region = cfg.region_m or (fence.xmin_m, fence.ymin_m, fence.xmax_m, fence.ymax_m)
        lattice = Lattice(region, step_m)
        start_cell = cfg.start_cell or lattice.cell_of(home_scene)
        for name, c in (("start", start_cell), ("target", cfg.target_cell)):
            if not lattice.contains(c):
                raise ConfigError(
                    f"{name} cell {c} is outside the lattice of shape {lattice.shape}"
                )
        start_pt = lattice.center(start_cell)
        target_pt = lattice.center(cfg.target_cell)
        start_xy, target_xy = (start_pt.x_m, start_pt.y_m), (target_pt.x_m, target_pt.y_m)
        fence.check(start_pt)

        renderer = WarpRenderer(scene, camera)
        target_img = renderer.render(target_pt.x_m, target_pt.y_m, alt_m, cfg.yaw_deg)
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
            p, alt = planner.to_scene(ned)
            fence.check(p)  # type: ignore[union-attr]
            if not (fence.min_alt_m - 0.5 <= alt <= fence.max_alt_m + 0.5):  # type: ignore[union-attr]
                raise SafetyViolation(f"setpoint altitude {alt:.1f} m outside the altitude band")

        pump = SetpointPump(
            vehicle,
            rate_hz=cfg.pump_rate_hz,
            deadline_s=cfg.policy_deadline_s,
            fence_check=fence_check,
            watchdog=watchdog,
            land_timeout_s=t.command_s,
        )
        report("take-off", 0.0)
        take_off(vehicle, pump, planner.to_ned(home_scene), cfg.yaw_deg, cfg.arrive_alt_tol_m, t)
        armed_once = True
        watchdog.engage()
        rec.event(f"airborne at {alt_m:.1f} m in {vehicle.state().mode}")
        report("take-off", 1.0)

        step_timeout = cfg.step_timeout_s or (3.0 * step_m / 2.0 + 10.0)
        # Fly to the start cell (a positioning leg, not a policy step).
        previous = start_pt
        ned = planner.to_ned(start_pt)
        pump.set_target(ned, cfg.yaw_deg)
        _wait_arrival(
            vehicle,
            pump,
            watchdog,
            ned,
            cfg,
            rec,
            planner,
            step_timeout + horizontal_distance_m(ned, vehicle.state().position or ned) / 2.0,
        )
        cell = start_cell
        rec.event(f"at start cell {cell}")
        policy.reset()
        while True:
            if cell == cfg.target_cell:
                success, reason = True, f"target cell {cfg.target_cell} reached in {steps} steps"
                break
            if steps >= cfg.max_steps:
                reason = f"step budget of {cfg.max_steps} spent at cell {cell}"
                break
            pump.raise_if_fault()
            state = vehicle.state()
            _check(watchdog, state)
            t_frame = time.perf_counter()
            image = frames.frame(state)
            action = int(policy.act(image, target_img))
            pump.tick()
            pump.raise_if_fault()
            steps += 1
            report("steps", steps / cfg.max_steps)
            if action not in ACTION_STEPS:
                raise FlightError(f"policy returned action {action}; expected 0..3")
            nxt = planner.next_target(previous, action, step_m)
            nxt_cell = lattice.cell_of(nxt)
            if not lattice.contains(nxt_cell):
                # As in the environment: a move out of the region leaves the agent in place.
                rec.write(
                    "step",
                    step=steps,
                    action=action,
                    action_name=ACTION_NAMES[action],
                    cell=cell,
                    blocked=True,
                    events=["move out of the lattice: stayed"],
                )
                continue
            ned = planner.to_ned(nxt)
            try:
                pump.set_target(ned, cfg.yaw_deg)
            except SafetyViolation as err:
                rec.write(
                    "step",
                    step=steps,
                    action=action,
                    action_name=ACTION_NAMES[action],
                    cell=cell,
                    target_scene=None,
                    refused_target=(nxt.x_m, nxt.y_m),
                    events=[f"geofence: {err}"],
                )
                raise
            latency_ms = (time.perf_counter() - t_frame) * 1000.0
            latencies.append(latency_ms)
            arrival_s, measured = _wait_arrival(
                vehicle, pump, watchdog, ned, cfg, rec, planner, step_timeout
            )
            m_scene, m_alt = planner.to_scene(measured)
            previous, cell = nxt, nxt_cell
            rec.write(
                "step",
                step=steps,
                action=action,
                action_name=ACTION_NAMES[action],
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
    except SafetyViolation as err:
        reason = f"safety: {err}"
        takeover = TAKEOVER in str(err)
        log.error("flight ended by a safety rule: %s", err)
        rec.event(reason)
    except FlightError as err:
        reason = f"{type(err).__name__}: {err}"
        log.error("flight ended: %s", reason)
        rec.event(reason)
    except KeyboardInterrupt as err:
        reason = "interrupted by the operator (Ctrl-C)"
        interrupted = err
        log.error("%s", reason)
        rec.event(reason)
    except Exception as err:  # any bug still ends in LAND/RTL below
        reason = f"unexpected error: {type(err).__name__}: {err}"
        log.exception("flight ended by an unexpected error")
        rec.event(reason)
        interrupted = err
    finally:
        end_action, disarmed = _finish(vehicle, pump, cfg, takeover, armed_once, rec)
        if frames is not None:
            frames.close()
    png = None
    try:
        png = rec.plot(scene, lattice, start_xy, target_xy, fence)
    except (OSError, ValueError) as err:
        log.warning("track plot failed: %s", err)
    rec.write(
        "result",
        success=success,
        reason=reason,
        steps=steps,
        final_cell=cell,
        end_action=end_action,
        disarmed=disarmed,
    )
    rec.close()
    try:
        vehicle.close()
    except FlightError as err:
        log.debug("closing vehicle: %s", err)
    report("done", 1.0)
    if interrupted is not None and isinstance(interrupted, KeyboardInterrupt):
        raise interrupted
    return FlightResult(
        success,
        reason,
        steps,
        cell,
        cfg.target_cell,
        end_action,
        disarmed,
        rec.path,
        png,
        latencies,
    )


def _check(watchdog: Watchdog, s: VehicleState) -> None:
    reason = watchdog.violation(s)
    if reason is not None:
        raise SafetyViolation(reason)


def _wait_arrival(
    vehicle: Vehicle,
    pump: SetpointPump,
    watchdog: Watchdog,
    target: LocalNED,
    cfg: FlightConfig,
    rec: FlightRecorder,
    planner: TargetPlanner,
    timeout_s: float,
) -> tuple[float, LocalNED]:
    """Wait until LOCAL_POSITION_NED is within tolerance of ``target`` AND slow.

    Returns:
        (seconds it took, the measured position).
    """
    t0 = time.monotonic()
    last_sample = 0.0
    while True:
        pump.tick()
        pump.raise_if_fault()
        s = vehicle.state()
        _check(watchdog, s)
        now = time.monotonic()
        if s.position is not None:
            if now - last_sample > 0.1:
                p, _ = planner.to_scene(s.position)
                rec.sample(p.x_m, p.y_m)
                last_sample = now
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
    cfg: FlightConfig,
    takeover: bool,
    armed_once: bool,
    rec: FlightRecorder,
) -> tuple[str, bool]:
    """Stop the stream, then LAND/RTL and wait for disarm (nothing after a takeover)."""
    if pump is not None:
        pump.stop()
    try:
        s = vehicle.state()
    except FlightError:
        return "none", False
    if takeover:
        rec.event("operator has control: no further commands from geonav")
        log.warning("operator took over (mode %s); geonav sends nothing more", s.mode)
        return "none", not s.armed
    if not s.armed and not armed_once:
        return "none", True
    try:
        s = end_flight(vehicle, cfg.end, cfg.timeouts)
        rec.event(f"{cfg.end} complete, disarmed")
        return cfg.end, not s.armed
    except FlightError as err:
        log.error("%s failed: %s; the autopilot's own failsafe must act", cfg.end.upper(), err)
        rec.event(f"{cfg.end} failed: {err}")
        try:
            return cfg.end, not vehicle.state().armed
        except FlightError:
            return cfg.end, False


def fly(
    policy: Policy | str | Path,
    scene: Any,
    *,
    target_cell: Cell,
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
    **config: Any,
) -> FlightResult:
    """Fly a checkpoint (or a Policy) on a scene; with ``dry_run`` against an in-process emulator.

    Args:
        policy: a checkpoint path or an object following :class:`Policy`.
        scene: a :class:`geonav.scene.Scene` or a scene package folder.
        target_cell: lattice cell to reach.
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
        **config: further :class:`FlightConfig` fields.
    """
    from geonav.scene import Scene

    if not isinstance(scene, Scene):
        scene = Scene.open(scene)
    pol: Policy = load_policy(policy) if isinstance(policy, (str, Path)) else policy
    cfg = FlightConfig(
        target_cell=tuple(target_cell),
        start_cell=start_cell,
        end=end,  # type: ignore[arg-type]
        camera=camera,
        **config,
    )
    emu = None
    if dry_run:
        from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig
        from geonav.tasks import Lattice

        step_m = float(cfg.step_m or pol.meta["step_m"])
        xmin, ymin, xmax, ymax = scene.bounds_m
        m = cfg.fence_margin_m
        lattice = Lattice(cfg.region_m or (xmin + m, ymin + m, xmax - m, ymax - m), step_m)
        if start_cell is None:
            start_cell = (lattice.shape[0] // 2, lattice.shape[1] // 2)
            cfg = FlightConfig(
                **{
                    **{f: getattr(cfg, f) for f in cfg.__dataclass_fields__},
                    "start_cell": start_cell,
                }
            )
        home = scene.frame.to_lonlat(lattice.center(start_cell), 0.0)
        # A dry run is a rehearsal, not a failsafe test: emulated time runs 3x faster and
        # PX4's offboard-loss timeout is 6 s (2 s wall), so the in-process emulator's GIL
        # sharing on a busy machine does not end the flight.
        ec = emulator_config or EmulatorConfig(
            autopilot=autopilot,
            offboard_loss_s=6.0,
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
        return run_flight(vehicle, scene, pol, cfg, out_dir, progress)
    finally:
        if emu is not None:
            emu.stop()


__all__ = [
    "FlightConfig",
    "FlightResult",
    "Policy",
    "ScenePoint",
    "ScriptedPolicy",
    "fly",
    "load_policy",
    "path_actions",
    "run_flight",
]
