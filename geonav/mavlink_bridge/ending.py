"""Phases 4 and 5 of a flight: the end action, then the record and the result.

:func:`end_action` stops the setpoint stream and, when geonav flies the vehicle, lands
or returns it, confirmed on the heartbeat, and waits for the disarm; after an
operator's takeover, an autopilot failsafe or a position loss (someone else has
control), or on a vehicle geonav never armed, it commands nothing. Then
:func:`clear_autopilot_fence` takes geonav's fence back from a vehicle on the ground.
:func:`record_result` decides the final outcome and its exit code, writes the record's
result row, closes the link, and returns the
:class:`~geonav.mavlink_bridge.outcome.FlightResult` whose track picture is drawn only
afterwards (:meth:`~geonav.mavlink_bridge.outcome.FlightResult.draw_track`), so the
result line and the exit code never wait for matplotlib.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from geonav.errors import FlightError
from geonav.mavlink_bridge.autonomy import Verdict
from geonav.mavlink_bridge.context import FlightContext
from geonav.mavlink_bridge.outcome import (
    HANDED_OVER,
    FlightResult,
    classify,
    exit_code_of,
    strip_outcome,
)
from geonav.mavlink_bridge.safety import LinkLost, OperatorTakeover, attribute_mode_change
from geonav.mavlink_bridge.sequence import end_flight
from geonav.mavlink_bridge.signals import StopSignals
from geonav.mavlink_bridge.vehicle import VehicleState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EndReport:
    """What the end action did.

    Attributes:
        action: ``land``, ``rtl`` or ``none``.
        disarmed: the vehicle was disarmed at the end.
        confirmed: LAND/RTL was confirmed on the heartbeat and the vehicle disarmed.
        outcome: an outcome that overrides the flight's (``takeover``, ``link_lost``), or None.
        note: what to add to the reason ("" for nothing).
    """

    action: str
    disarmed: bool
    confirmed: bool = False
    outcome: str | None = None
    note: str = ""


def end_action(ctx: FlightContext, verdict: Verdict) -> EndReport:
    """Stop the stream, then LAND/RTL confirmed on the heartbeat and wait for disarm.

    Nothing is commanded when someone else has control, or on a vehicle geonav never
    armed.
    """
    cfg = ctx.cfg
    if ctx.pump is not None:
        ctx.pump.stop()
    try:
        s = ctx.vehicle.state()
    except FlightError:
        return EndReport("none", False)
    if verdict.outcome in HANDED_OVER:
        return _hand_over(ctx, verdict)
    if not ctx.we_fly:
        return EndReport("none", not s.armed)
    try:
        s = end_flight(ctx.vehicle, cfg.end, ctx.t, ctx.watchdog,
                       lambda st: ctx.sample(st, "landing"))
        ctx.rec.event(f"{cfg.end} confirmed on the heartbeat, disarmed")
        return EndReport(cfg.end, not s.armed, True)
    except OperatorTakeover as err:
        err = attribute_mode_change(ctx.vehicle, err)
        log.info("%s", err)
        ctx.rec.event(str(err))
        return EndReport(cfg.end, False, False, classify(err, ctx.phase), str(err))
    except LinkLost as err:
        log.info("%s", err)
        ctx.rec.event(f"{cfg.end} failed: {err}")
        return EndReport(cfg.end, False, False, "link_lost", str(err))
    except FlightError as err:
        note = f"{cfg.end.upper()} failed: {err}; the autopilot's own failsafe must act"
        log.info("%s", note)
        ctx.rec.event(note)
        try:
            return EndReport(cfg.end, not ctx.vehicle.state().armed, False, None, note)
        except FlightError:
            return EndReport(cfg.end, False, False, None, note)


#: after a position loss, how long geonav watches for the autopilot's own failsafe mode.
HANDOVER_WATCH_S = 5.0


def _hand_over(ctx: FlightContext, verdict: Verdict) -> EndReport:
    """Someone else has control: command nothing. An operator flies on; the autopilot's
    failsafe (or, after a position loss, the failsafe geonav leaves it to) is watched
    until the vehicle is down, so the record holds the landing and the fence can be
    cleared."""
    who = "operator" if verdict.outcome == "takeover" else "autopilot"
    ctx.rec.event(f"{who} has control: no further commands from geonav")
    s = ctx.vehicle.state()
    if verdict.outcome == "takeover":
        log.info("the operator has control (mode %s); geonav sends nothing more", s.mode)
        return EndReport("none", not s.armed)
    notes = []
    if verdict.outcome == "position_lost":
        s = _await(ctx, lambda st: st.mode != s.mode or not st.armed, HANDOVER_WATCH_S)
        notes.append("geonav stopped commanding; " + (
            f"the autopilot's failsafe has control (mode {s.mode})" if s.mode != _flying(ctx)
            else f"the vehicle still shows {s.mode}: the autopilot's failsafe must act"))
    s = _await(ctx, lambda st: not st.armed, ctx.t.landing_s)
    if not s.armed:
        notes.append("the autopilot landed, disarmed")
    elif s.heartbeat_age_s > ctx.cfg.heartbeat_timeout_s:
        notes.append("then the link was lost")
    else:
        notes.append(f"the vehicle still flies (mode {s.mode}) after {ctx.t.landing_s:.0f} s")
    note = "; ".join(notes)
    ctx.rec.event(note)
    return EndReport("none", not s.armed, note=note)


def _flying(ctx: FlightContext) -> str:
    """The mode geonav flies in."""
    return ctx.watchdog.autonomy_mode if ctx.watchdog is not None else ""


def _await(ctx: FlightContext, done: Callable[[VehicleState], bool],
           timeout_s: float) -> VehicleState:
    """Watch the vehicle (track sampled as the landing) until ``done``, the timeout, or
    a silent link."""
    deadline = time.monotonic() + timeout_s
    s = ctx.vehicle.state()
    while not done(s) and time.monotonic() < deadline \
            and s.heartbeat_age_s <= ctx.cfg.heartbeat_timeout_s:
        ctx.sample(s, "landing")
        time.sleep(0.1)
        s = ctx.vehicle.state()
    return s


def clear_autopilot_fence(ctx: FlightContext) -> None:
    """Take geonav's fence back from the autopilot once the vehicle is on the ground
    (disarmed); a vehicle someone else still flies keeps it, and the record says so."""
    if not ctx.fence_uploaded:
        return
    try:
        s = ctx.vehicle.state()
        if s.armed:
            note = "the autopilot keeps geonav's fence while it flies (clear it from a GCS)"
            log.info("%s", note)
            ctx.notes.append(note)
            ctx.rec.event(note)
            return
        if s.heartbeat_age_s > ctx.cfg.heartbeat_timeout_s:
            ctx.rec.event("autopilot fence not cleared: no link")
            return
        ctx.vehicle.clear_fence(3.0 * ctx.t.command_s)
        ctx.fence_uploaded = False
        ctx.rec.event("autopilot fence cleared, its parameters restored")
    except FlightError as err:
        note = f"clearing the autopilot fence failed ({err}); clear it from a GCS"
        log.warning("%s", note)
        ctx.notes.append(note)
        ctx.rec.event(note)


def record_result(ctx: FlightContext, verdict: Verdict, end: EndReport,
                  sigs: StopSignals) -> FlightResult:
    """The final outcome (the end action may override it), the result row, the link
    closed; the track picture is left to :meth:`FlightResult.draw_track`."""
    outcome, reason = verdict.outcome, verdict.reason
    if end.outcome is not None and outcome in ("reached", "missed", "safety_stop"):
        outcome = end.outcome
    if end.note:
        note = end.note
        if reason and end.outcome is not None:
            # The outcome words head the summary once: "link lost: <why the flight
            # ended>; no autopilot heartbeat ...", not "...; link lost: no ..." (PX4 SIH).
            note = strip_outcome(end.outcome, note)
        reason = f"{reason}; {note}" if reason else note
    signal_name = None
    if sigs.received is not None:
        signal_name = signal.Signals(sigs.received).name
        if outcome != "interrupted":
            ctx.rec.event(f"{signal_name} received while ending the flight")
    rec = ctx.rec
    try:
        battery_pct = ctx.vehicle.state().battery_pct
    except FlightError:
        battery_pct = None
    rec.write(
        "result",
        success=verdict.success,
        outcome=outcome,
        exit_code=exit_code_of(outcome, signal_name),  # 143 for SIGTERM, as the process exits
        reason=reason,
        steps=ctx.steps,
        flown_steps=ctx.flown_steps,
        final_cell=ctx.cell,
        battery_pct=battery_pct,
        end_action=end.action,
        end_ok=end.confirmed,
        disarmed=end.disarmed,
        signal=signal_name,
        notes=ctx.notes,
    )
    rec.close()
    try:
        ctx.vehicle.close()
    except Exception as err:  # noqa: BLE001 - closing never ends in a traceback
        log.debug("closing vehicle: %s", err)
    ctx.report("done", 1.0)

    def draw() -> Path | None:
        # After the result is recorded and returned: drawing waits for nothing the
        # flight decides (matplotlib on a loaded machine took 30-70 s).
        try:
            return rec.plot(ctx.scene, ctx.plan.lattice, ctx.start_xy, ctx.target_xy, ctx.fence)
        except (OSError, ValueError) as err:
            log.warning("track plot failed: %s", err)
            return None

    return FlightResult(
        verdict.success, reason, ctx.steps, ctx.cell, ctx.cfg.target_cell, end.action,
        end.disarmed, rec.path, None, ctx.latencies_ms, outcome=outcome,
        end_ok=end.confirmed, signal_name=signal_name if outcome == "interrupted" else None,
        notes=ctx.notes, flown_steps=ctx.flown_steps, fence_kept=ctx.fence_uploaded,
        _draw=draw,
    )
