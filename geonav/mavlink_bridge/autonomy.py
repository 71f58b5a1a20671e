"""Phases 2 and 3 of a flight: take-off and positioning, then the policy's steps.

:func:`take_off_and_position` arms and climbs to the policy's altitude in the autonomy
mode (or takes an airborne vehicle over where it is) and flies to the start cell;
:func:`step_loop` then runs the policy: frame, action, next lattice target (previous
target plus one step, refused if off the lattice, on an obstacle or off the fence),
arrival (distance and speed under thresholds), one record row per step. Both run the
watchdog, the track sample and the position fence in every wait.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from geonav.errors import FlightError, FlightTimeout, SafetyViolation
from geonav.geo import LocalNED, ScenePoint
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.context import FlightContext
from geonav.mavlink_bridge.conversion import ACTION_NAMES, ACTION_STEPS
from geonav.mavlink_bridge.sequence import horizontal_distance_m, set_mode_confirmed, take_off

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Verdict:
    """How the flight ended before the end action: outcome word, reason, success."""

    outcome: str
    reason: str
    success: bool = False


def take_off_and_position(ctx: FlightContext) -> None:
    """Arm and climb (or take over where the vehicle flies), then fly to the start cell."""
    assert ctx.pump is not None and ctx.watchdog is not None and ctx.planner is not None
    ctx.report("take-off", 0.0)
    if ctx.airborne:
        _take_over(ctx)
    else:
        _arm_and_climb(ctx)
    ctx.phase = "autonomy"
    ctx.watchdog.engage()
    ctx.rec.event(f"airborne at {ctx.alt_m:.1f} m in {ctx.vehicle.state().mode}")
    ctx.report("take-off", 1.0)
    # Fly to the start cell (a positioning leg, not a policy step).
    assert ctx.start_pt is not None
    ned = ctx.planner.to_ned(ctx.start_pt)
    ctx.pump.set_target(ned, ctx.cfg.yaw_deg)
    leg_m = horizontal_distance_m(ned, ctx.vehicle.state().position or ned)
    wait_arrival(ctx, ned, step_timeout_s(ctx) + leg_m / 2)
    ctx.cell = ctx.start_cell
    ctx.rec.event(f"at start cell {ctx.cell}")


def _take_over(ctx: FlightContext) -> None:
    """Hold the airborne vehicle where it is, then switch to the autonomy mode."""
    assert ctx.pump is not None and ctx.watchdog is not None and ctx.planner is not None
    assert ctx.here_scene is not None
    ctx.phase = "takeover"
    ctx.we_fly = True
    s = ctx.vehicle.state()
    assert s.position is not None
    hold = ctx.planner.to_ned(ctx.here_scene)
    ctx.pump.set_target(LocalNED(s.position.north_m, s.position.east_m, hold.down_m), 0.0)
    ctx.pump.start()
    if ctx.vehicle.autopilot == M.PX4:
        time.sleep(min(1.2, ctx.t.mode_s / 2))
    set_mode_confirmed(ctx.vehicle, ctx.watchdog.autonomy_mode, ctx.t, ctx.pump.tick,
                       ctx.watchdog)


def _arm_and_climb(ctx: FlightContext) -> None:
    """Arm in the autonomy mode and climb over the take-off point."""
    assert ctx.pump is not None and ctx.planner is not None and ctx.here_scene is not None
    ctx.phase = "arming"

    def armed() -> None:
        ctx.phase, ctx.we_fly = "takeoff", True

    take_off(
        ctx.vehicle,
        ctx.pump,
        ctx.planner.to_ned(ctx.here_scene),
        ctx.cfg.yaw_deg,
        ctx.cfg.arrive_alt_tol_m,
        ctx.t,
        watchdog=ctx.watchdog,
        check=ctx.in_flight_check,
        on_armed=armed,
    )


def step_timeout_s(ctx: FlightContext) -> float:
    """Seconds allowed per lattice step (``step_timeout_s`` or 3 * step / 2 m/s + 10 s)."""
    return ctx.cfg.step_timeout_s or (3.0 * ctx.plan.step_m / 2.0 + 10.0)


def wait_arrival(ctx: FlightContext, target: LocalNED, timeout_s: float) -> tuple[float, LocalNED]:
    """Wait until LOCAL_POSITION_NED is within tolerance of ``target`` AND slow.

    The pump, the watchdog, the track sample and the position fence run every cycle.

    Returns:
        (seconds it took, the measured position).

    Raises:
        FlightTimeout: not arrived within ``timeout_s``.
    """
    assert ctx.pump is not None and ctx.watchdog is not None
    cfg = ctx.cfg
    t0 = time.monotonic()
    while True:
        ctx.pump.tick()
        ctx.pump.raise_if_fault()
        s = ctx.vehicle.state()
        ctx.watchdog.check(s)
        ctx.in_flight_check()
        now = time.monotonic()
        if s.position is not None:
            d_h = horizontal_distance_m(s.position, target)
            d_v = abs(s.position.down_m - target.down_m)
            if (d_h <= cfg.arrive_tol_m and d_v <= cfg.arrive_alt_tol_m
                    and s.speed_mps <= cfg.arrive_speed_mps):
                return now - t0, s.position
        if now - t0 > timeout_s:
            raise FlightTimeout(
                f"not arrived at NED ({target.north_m:.1f}, {target.east_m:.1f}, "
                f"{target.down_m:.1f}) within {timeout_s:.1f} s (last position {s.position}, "
                f"speed {s.speed_mps:.2f} m/s)"
            )
        time.sleep(0.02)


def step_loop(ctx: FlightContext) -> Verdict:
    """Run the policy from the start cell until the target, the step budget or a fault.

    A step counts once it is done and recorded (a refused move counts: the env counts
    it too); a step cut short by a link loss or an error is not counted.

    Raises:
        FlightError: any fault (the driver classifies it and ends the flight).
    """
    cfg = ctx.cfg
    assert ctx.start_pt is not None
    previous = ctx.start_pt
    ctx.policy.reset()
    while True:
        if ctx.cell == cfg.target_cell:
            return Verdict("reached", f"target cell {cfg.target_cell} reached in "
                           f"{ctx.steps} steps", success=True)
        if ctx.steps >= cfg.max_steps:
            return Verdict("missed", f"step budget of {cfg.max_steps} spent at cell {ctx.cell}")
        previous = _one_step(ctx, previous)
        ctx.report("steps", ctx.steps / cfg.max_steps)


def _one_step(ctx: FlightContext, previous: ScenePoint) -> ScenePoint:
    """Frame -> action -> target -> arrival; returns the new previous target."""
    assert ctx.pump is not None and ctx.watchdog is not None and ctx.planner is not None
    assert ctx.frames is not None
    cfg, plan, lattice = ctx.cfg, ctx.plan, ctx.plan.lattice
    ctx.pump.raise_if_fault()
    state = ctx.vehicle.state()
    ctx.watchdog.check(state)
    ctx.check_position(state)
    ctx.check_battery(state)  # no new step on a battery below --min-battery
    t_frame = time.perf_counter()
    image = ctx.frames.frame(state)
    action = int(ctx.policy.act(image, ctx.target_img))
    ctx.pump.tick()
    ctx.pump.raise_if_fault()
    n = ctx.steps + 1
    if action not in ACTION_STEPS:
        raise FlightError(f"policy returned action {action}; expected 0..3")
    nxt = ctx.planner.next_target(previous, action, plan.step_m)
    nxt_cell = lattice.cell_of(nxt)
    base = dict(step=n, action=action, action_name=ACTION_NAMES[action])
    if not lattice.contains(nxt_cell):
        # As in the environment: a move out of the region leaves the agent in place.
        ctx.rec.write("step", **base, cell=ctx.cell, blocked=True,
                      events=["move out of the lattice: stayed"])
        ctx.steps = n
        return previous
    if plan.blocked[nxt_cell]:
        _refuse_obstacle(ctx, base, nxt_cell)
        ctx.steps = n
        return previous
    ned = ctx.planner.to_ned(nxt)
    try:
        ctx.pump.set_target(ned, cfg.yaw_deg)
    except SafetyViolation as err:
        ctx.rec.write("step", **base, cell=ctx.cell, target_scene=None,
                      refused_target=(nxt.x_m, nxt.y_m), events=[f"geofence: {err}"])
        ctx.steps = n  # recorded: it ended the flight where it stands
        raise
    latency_ms = (time.perf_counter() - t_frame) * 1000.0
    ctx.latencies_ms.append(latency_ms)
    arrival_s, measured = wait_arrival(ctx, ned, step_timeout_s(ctx))
    m_scene, m_alt = ctx.planner.to_scene(measured)
    ctx.cell = nxt_cell
    ctx.flown_steps += 1
    ctx.rec.write(
        "step", **base, cell=ctx.cell, target_scene=(nxt.x_m, nxt.y_m),
        target_ned=(ned.north_m, ned.east_m, ned.down_m),
        measured_ned=(measured.north_m, measured.east_m, measured.down_m),
        measured_scene=(m_scene.x_m, m_scene.y_m), measured_alt_m=m_alt,
        arrival_s=round(arrival_s, 3), latency_ms=round(latency_ms, 3),
        battery_pct=ctx.vehicle.state().battery_pct, events=[],
    )
    ctx.steps = n
    return nxt


def _refuse_obstacle(ctx: FlightContext, base: dict[str, object], cell: tuple[int, int]) -> None:
    """A move into a DSM obstacle: refused (the vehicle stays) or, with
    ``--on-obstacle end``, the end of the flight."""
    text = (f"obstacle: cell {cell} is blocked at {ctx.alt_m:g} m (DSM, "
            "env rule geonav.tasks.blocked_cells)")
    if ctx.cfg.on_obstacle == "end":
        ctx.rec.write("step", **base, cell=ctx.cell, blocked=True,
                      events=[f"{text}: flight ended (--on-obstacle end)"])
        ctx.steps += 1  # the step is done: it ended the flight where it stands
        raise SafetyViolation(f"{text}; --on-obstacle end")
    ctx.rec.write("step", **base, cell=ctx.cell, blocked=True,
                  events=[f"{text}: refused, kept position (--on-obstacle stay)"])
    log.warning("%s: move refused, vehicle keeps its position", text)
