"""Phase 1 of a flight: connect and check everything before anything arms.

:func:`preflight` connects, waits for the autopilot to be ready, refuses a vehicle
someone else is flying (unless ``takeover_airborne``), requests telemetry, waits for
the EKF origin and a position, refuses a battery below ``--min-battery``, then places
the flight: the frame conversion, the fence (the vehicle, the start and the target
inside it), the start cell, the target view and a policy check, the camera, the safety
machinery (watchdog, setpoint pump), and last the autopilot's own copy of the fence
(items over the mission protocol, its breach action by parameter). Every refusal is a
:class:`~geonav.mavlink_bridge.safety.PreflightRefused` raised before a single command
that moves the vehicle.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace

from geonav.errors import CheckpointError, ConfigError, FlightError
from geonav.geo import ScenePoint
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.camera_source import OpenCVFrames, SyntheticFrames, parse_camera
from geonav.mavlink_bridge.context import FlightContext
from geonav.mavlink_bridge.conversion import TargetPlanner
from geonav.mavlink_bridge.plan import plan_flight
from geonav.mavlink_bridge.pump import SetpointPump
from geonav.mavlink_bridge.safety import Geofence, PreflightRefused, Watchdog
from geonav.mavlink_bridge.sequence import wait_position, wait_ready
from geonav.mavlink_bridge.vehicle import FenceSpec, VehicleState

log = logging.getLogger(__name__)

MIN_TAKEOVER_ALT_M = 1.0
"""--takeover-airborne refuses a vehicle lower than this above home (armed on the ground)."""

_AIRBORNE_STATES = (
    M.MAV_LANDED_STATE_IN_AIR,
    M.MAV_LANDED_STATE_TAKEOFF,
    M.MAV_LANDED_STATE_LANDING,
)


def preflight(ctx: FlightContext) -> None:
    """Connect, check and place the flight; set up the watchdog and the pump.

    Raises:
        PreflightRefused: the vehicle, home, the start or the policy is unfit to fly.
        FlightTimeout: the autopilot never got ready or never had a position.
    """
    s = connect(ctx)
    check_battery(ctx)
    home_down = home_down_m(ctx, s)
    place(ctx, s, home_down)
    prepare_views(ctx)
    make_safety(ctx)
    upload_autopilot_fence(ctx)


#: how long preflight waits for a first battery reading.
BATTERY_WAIT_S = 3.0


def check_battery(ctx: FlightContext) -> None:
    """Refuse a battery below ``--min-battery`` (a vehicle that says nothing of its
    battery is flown, with a warning that the floor is not enforced)."""
    floor = ctx.cfg.min_battery_pct
    if floor <= 0:
        return
    deadline = time.monotonic() + BATTERY_WAIT_S
    s = ctx.vehicle.state()
    while s.battery_pct is None:
        if time.monotonic() > deadline:
            note = ("no battery reading from the autopilot (SYS_STATUS, BATTERY_STATUS): "
                    "--min-battery is not enforced")
            log.warning("%s", note)
            ctx.notes.append(note)
            ctx.rec.event(note)
            return
        time.sleep(0.1)
        s = ctx.vehicle.state()
    ctx.rec.battery(s.battery_pct, s.battery_v)
    if s.battery_pct < floor:
        raise PreflightRefused(
            f"battery at {s.battery_pct:.0f}% is below --min-battery {floor:g}%: charge or "
            "change it (or lower --min-battery)"
        )


def connect(ctx: FlightContext) -> VehicleState:
    """Connect, wait for STANDBY, refuse someone else's vehicle, request telemetry,
    wait for the origin and a position; sets ``ctx.airborne``."""
    cfg, t, vehicle = ctx.cfg, ctx.t, ctx.vehicle
    ctx.report("connect", 0.0)
    vehicle.connect(t.connect_s)
    ctx.rec.event(f"connected: {vehicle.autopilot}")
    s = wait_ready(vehicle, t)
    if s.armed and not cfg.takeover_airborne:
        raise PreflightRefused(
            f"the vehicle is already armed (mode {s.mode}): geonav does not take over a "
            "vehicle someone else is flying; disarm it, or pass --takeover-airborne to "
            "start from its current position and altitude"
        )
    vehicle.request_telemetry(cfg.telemetry_rate_hz, t.command_s)
    s = wait_position(vehicle, t, set_origin=ctx.scene.origin if cfg.set_origin else None)
    assert s.origin is not None and s.position is not None
    airborne = s.armed or s.landed_state in _AIRBORNE_STATES
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
    ctx.airborne = airborne
    ctx.rec.event(f"EKF origin {s.origin}; position NED {s.position}")
    ctx.report("connect", 1.0)
    return s


def home_down_m(ctx: FlightContext, s: VehicleState) -> float:
    """The take-off point's down coordinate; for a takeover, re-plan at the vehicle's
    altitude (the take-off point is home, and the EKF origin is usually there too)."""
    assert s.position is not None and s.origin is not None
    if not ctx.airborne:
        return s.position.down_m
    home_down = s.origin.alt_m - s.home.alt_m if s.home is not None else 0.0
    alt_m = float(home_down - s.position.down_m)
    if alt_m < MIN_TAKEOVER_ALT_M:
        raise PreflightRefused(
            f"the vehicle is armed but on the ground ({alt_m:.1f} m above home): "
            "--takeover-airborne takes over a vehicle in the air; disarm it, or fly "
            f"it above {MIN_TAKEOVER_ALT_M:g} m first")
    ctx.rec.event(f"taking over an airborne vehicle at {alt_m:.1f} m above home")
    try:
        plan = plan_flight(ctx.scene, ctx.policy.meta,
                           replace(ctx.cfg, alt_m=alt_m, start_cell=None))
    except ConfigError as err:
        raise PreflightRefused(f"taking over at {alt_m:.1f} m: {err}") from err
    # Flown at the altitude it has (a clamp by --max-alt is then refused by the fence band).
    ctx.plan = replace(plan, alt_m=alt_m)
    return home_down


def place(ctx: FlightContext, s: VehicleState, home_down: float) -> None:
    """Frame conversion, fence, start and target: the vehicle, the climb, the start
    and the target must all lie inside the fence and off the obstacles."""
    assert s.position is not None and s.origin is not None
    cfg, plan = ctx.cfg, ctx.plan
    lattice, alt_m = plan.lattice, plan.alt_m
    ctx.planner = TargetPlanner(ctx.scene.frame, s.origin, home_down, alt_m, cfg.yaw_deg,
                                autopilot=ctx.vehicle.autopilot)
    here, _ = ctx.planner.to_scene(s.position)
    ctx.here_scene = here
    fence = ctx.fence = Geofence.from_bounds(
        ctx.scene.bounds_m, plan.margin_m, home=here, max_distance_m=cfg.max_distance_m,
        max_alt_m=cfg.max_alt_m, overshoot_m=plan.margin_m / 2.0,
    )
    why = fence.violation(here)
    if why is not None:
        raise PreflightRefused(f"the vehicle is outside the scene fence: {why}")
    if not fence.min_alt_m <= alt_m <= fence.max_alt_m:
        raise PreflightRefused(
            f"flight altitude {alt_m:.1f} m is outside the fence's {fence.min_alt_m:g}.."
            f"{fence.max_alt_m:g} m band"
        )
    start_cell = (cfg.start_cell if not ctx.airborne else None) or lattice.cell_of(here)
    if not lattice.contains(start_cell) or plan.blocked[start_cell]:
        raise PreflightRefused(
            f"start cell {start_cell} is outside the lattice {lattice.shape} or an obstacle "
            f"at {alt_m:g} m"
        )
    here_cell = lattice.cell_of(here)
    if lattice.contains(here_cell) and plan.blocked[here_cell]:
        raise PreflightRefused(
            f"the take-off point's cell {here_cell} is an obstacle at {alt_m:g} m: "
            "the climb would hit it"
        )
    ctx.start_cell = start_cell
    ctx.start_pt, ctx.target_pt = lattice.center(start_cell), lattice.center(cfg.target_cell)
    for name, pt in (("start", ctx.start_pt), ("target", ctx.target_pt)):
        why = fence.violation(pt)
        if why is not None:
            raise PreflightRefused(
                f"{name} cell is outside the geofence ({why}); fence margin "
                f"{plan.margin_m:g} m (--fence-margin)"
            )


def prepare_views(ctx: FlightContext) -> None:
    """The target's view, a policy that must be able to act on the scene's views, and
    the camera (synthetic renders at the reported position, or OpenCV)."""
    from geonav.camera import Camera, WarpRenderer

    assert ctx.start_pt is not None and ctx.target_pt is not None and ctx.planner is not None
    meta, cfg, alt_m = ctx.policy.meta, ctx.cfg, ctx.alt_m
    size_px = int(meta.get("obs_size_px", 84))
    camera = Camera(size_px=size_px, fov_deg=float(meta.get("fov_deg", 90.0)))
    renderer = WarpRenderer(ctx.scene, camera)
    ctx.target_img = renderer.render(ctx.target_pt.x_m, ctx.target_pt.y_m, alt_m, cfg.yaw_deg)
    check = getattr(ctx.policy, "check_outputs", None)
    if check is not None:  # a policy that cannot act is refused before anything arms
        try:
            check(renderer.render(ctx.start_pt.x_m, ctx.start_pt.y_m, alt_m, cfg.yaw_deg),
                  ctx.target_img)
        except CheckpointError as err:
            raise PreflightRefused(str(err)) from err
    if ctx.frames is None:
        kind, dev = parse_camera(cfg.camera)
        ctx.frames = (
            SyntheticFrames(renderer, ctx.planner.to_scene, cfg.yaw_deg)
            if kind == "synthetic"
            else OpenCVFrames(dev if dev is not None else 0, size_px)
        )


def make_safety(ctx: FlightContext) -> None:
    """The link/mode/position watchdog and the setpoint pump that refuses targets off
    the fence. The GPS fix is watched when the vehicle has a 3D fix now."""
    cfg = ctx.cfg
    ctx.watchdog = Watchdog(cfg.heartbeat_timeout_s, cfg.position_timeout_s,
                            M.AUTONOMY_MODE[ctx.vehicle.autopilot])
    fix = ctx.vehicle.state().gps_fix_type
    ctx.watchdog.gps_required = fix is not None and fix >= 3
    ctx.pump = SetpointPump(
        ctx.vehicle,
        rate_hz=cfg.pump_rate_hz,
        deadline_s=cfg.policy_deadline_s,
        fence_check=ctx.check_setpoint,
        watchdog=ctx.watchdog,
        land_timeout_s=ctx.t.command_s,
    )


#: the autopilot's ceiling is this far above geonav's ``--max-alt``.
FENCE_CEILING_MARGIN_M = 5.0


def autopilot_fence(ctx: FlightContext) -> FenceSpec:
    """The autopilot's fence: the scene's edge (geonav's setpoints stay one fence margin
    inside it, so no step's overshoot reaches it), a circle of ``--max-distance`` plus the
    margin around home, the ceiling, and the end action as its breach action."""
    assert ctx.here_scene is not None
    scene, cfg = ctx.scene, ctx.cfg
    xmin, ymin, xmax, ymax = scene.bounds_m
    corners = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
    polygon = tuple(scene.frame.to_lonlat(ScenePoint(x, y), 0.0) for x, y in corners)
    circle = None
    if math.isfinite(cfg.max_distance_m):
        circle = (scene.frame.to_lonlat(ctx.here_scene, 0.0),
                  cfg.max_distance_m + ctx.plan.margin_m)
    return FenceSpec(polygon, circle, cfg.max_alt_m + FENCE_CEILING_MARGIN_M, cfg.end)


def upload_autopilot_fence(ctx: FlightContext) -> None:
    """Give the autopilot the fence (before arming; :func:`ending.clear_autopilot_fence`
    takes it back after the landing).

    Raises:
        PreflightRefused: the autopilot would not take it.
    """
    if not ctx.cfg.autopilot_fence:
        ctx.rec.event("the autopilot gets no fence (--no-autopilot-fence): geonav's only")
        return
    fence = autopilot_fence(ctx)
    ctx.fence_uploaded = True  # cleared at the end even if only part of it went through
    try:
        ctx.vehicle.upload_fence(fence, 3.0 * ctx.t.command_s)
    except FlightError as err:
        raise PreflightRefused(
            f"the autopilot did not take geonav's fence ({err}); fly with "
            "--no-autopilot-fence to rely on geonav's own fence alone"
        ) from err
    ctx.rec.event(f"autopilot fence: {len(fence.polygon)}-vertex polygon"
                  + (f", {fence.circle[1]:.0f} m circle" if fence.circle else "")
                  + f", ceiling {fence.max_alt_m:g} m, breach action {fence.action}")
