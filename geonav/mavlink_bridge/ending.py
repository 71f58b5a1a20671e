"""Phases 4 and 5 of a flight: the end action, then the record and the result.

:func:`end_action` stops the setpoint stream and, when geonav flies the vehicle, lands
or returns it, confirmed on the heartbeat, and waits for the disarm; after an
operator's (or an autopilot's) takeover, or on a vehicle geonav never armed, it
commands nothing. :func:`record_result` decides the final outcome and its exit code,
writes the record's result row, closes the link, and returns the
:class:`~geonav.mavlink_bridge.outcome.FlightResult` whose track picture is drawn only
afterwards (:meth:`~geonav.mavlink_bridge.outcome.FlightResult.draw_track`), so the
result line and the exit code never wait for matplotlib.
"""

from __future__ import annotations

import logging
import signal
from dataclasses import dataclass
from pathlib import Path

from geonav.errors import FlightError
from geonav.mavlink_bridge.autonomy import Verdict
from geonav.mavlink_bridge.context import FlightContext
from geonav.mavlink_bridge.outcome import FlightResult, exit_code_of, strip_outcome
from geonav.mavlink_bridge.safety import LinkLost, OperatorTakeover
from geonav.mavlink_bridge.sequence import end_flight
from geonav.mavlink_bridge.signals import StopSignals

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


def end_action(ctx: FlightContext, takeover: bool) -> EndReport:
    """Stop the stream, then LAND/RTL confirmed on the heartbeat and wait for disarm.

    Nothing is commanded after a takeover, or on a vehicle geonav never armed.
    """
    cfg = ctx.cfg
    if ctx.pump is not None:
        ctx.pump.stop()
    try:
        s = ctx.vehicle.state()
    except FlightError:
        return EndReport("none", False)
    if takeover:
        ctx.rec.event("operator has control: no further commands from geonav")
        log.warning("someone else has control (mode %s); geonav sends nothing more", s.mode)
        return EndReport("none", not s.armed)
    if not ctx.we_fly:
        return EndReport("none", not s.armed)
    try:
        s = end_flight(ctx.vehicle, cfg.end, ctx.t, ctx.watchdog,
                       lambda st: ctx.sample(st, "landing"))
        ctx.rec.event(f"{cfg.end} confirmed on the heartbeat, disarmed")
        return EndReport(cfg.end, not s.armed, True)
    except OperatorTakeover as err:
        log.warning("%s", err)
        ctx.rec.event(str(err))
        return EndReport(cfg.end, False, False, "takeover", str(err))
    except LinkLost as err:
        log.error("%s", err)
        ctx.rec.event(f"{cfg.end} failed: {err}")
        return EndReport(cfg.end, False, False, "link_lost", str(err))
    except FlightError as err:
        note = f"{cfg.end.upper()} failed: {err}; the autopilot's own failsafe must act"
        log.error("%s", note)
        ctx.rec.event(note)
        try:
            return EndReport(cfg.end, not ctx.vehicle.state().armed, False, None, note)
        except FlightError:
            return EndReport(cfg.end, False, False, None, note)


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
    rec.write(
        "result",
        success=verdict.success,
        outcome=outcome,
        exit_code=exit_code_of(outcome, signal_name),  # 143 for SIGTERM, as the process exits
        reason=reason,
        steps=ctx.steps,
        final_cell=ctx.cell,
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
        notes=ctx.notes, _draw=draw,
    )
