"""How a flight ended: the outcome words, their exit codes, and the result record.

Every flight ends with one :data:`OUTCOMES` word; :class:`FlightResult` carries it with
the reason, the steps flown and the end action, says it in one console line
(:meth:`FlightResult.summary`) and gives the process exit code. :func:`classify` maps a
flight error raised in a phase to its outcome word.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from geonav.errors import CommandRejected, FlightError, FlightTimeout, SafetyViolation
from geonav.mavlink_bridge.safety import (
    AutopilotFailsafe,
    BatteryLow,
    LinkLost,
    OperatorTakeover,
    PositionLost,
    PreflightRefused,
)

Cell = tuple[int, int]

#: outcome -> process exit code (2 stays "bad input" for the CLI; signals give 128 + N).
OUTCOMES: dict[str, int] = {
    "reached": 0,
    "missed": 1,
    "refused": 3,
    "link_lost": 4,
    "takeover": 5,
    "safety_stop": 6,
    "failsafe": 7,
    "position_lost": 8,
    "interrupted": 130,
}
OUTCOME_WORDS = {
    "reached": "reached the target",
    "missed": "did not reach the target",
    "refused": "refused before arming",
    "link_lost": "link lost",
    "takeover": "operator took over",
    "safety_stop": "safety stop",
    "failsafe": "autopilot failsafe",
    "position_lost": "position lost",
    "interrupted": "interrupted",
}
#: outcomes after which someone else has control: geonav commands no end action.
HANDED_OVER = ("takeover", "failsafe", "position_lost")


@dataclass
class FlightResult:
    """What happened.

    Attributes:
        success: the vehicle arrived at the target cell.
        reason: why the flight ended (target reached, step budget, the safety rule, the error).
        steps: policy steps taken (a move refused as in the env counts, as there).
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
        flown_steps: steps that moved the vehicle to a new cell (None: same as ``steps``).
        fence_kept: geonav's fence is still on the autopilot (it was flying, someone
            else's, at the end, or the link was gone).
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
    flown_steps: int | None = None
    fence_kept: bool = False
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
        return exit_code_of(self.outcome, self.signal_name)

    def summary(self) -> str:
        """One line for the console."""
        who = "the operator" if self.outcome == "takeover" else "the autopilot"
        if self.end_action == "none":
            has = self.outcome in HANDED_OVER
            end = f"no end action ({who + ' has control' if has else 'nothing flown'})"
        elif self.end_ok:
            end = f"end {self.end_action} confirmed, disarmed"
        elif self.outcome in HANDED_OVER:  # the mode changed during the landing
            end = f"end {self.end_action} stopped by {who} ({who} has control)"
        else:
            end = f"end {self.end_action} NOT confirmed (disarmed {self.disarmed})"
            if "failsafe must act" not in self.reason:  # said once
                end += "; the autopilot's failsafe must act"
        words = OUTCOME_WORDS[self.outcome]
        # "operator took over: mode changed to 'hold' ...", not "operator took over:
        # operator takeover: mode changed ..." (PX4 SIH and ArduCopter SITL).
        reason = strip_outcome(self.outcome, self.reason)
        head = reason if reason.lower().startswith(words) else f"{words}: {reason}"
        if self.fence_kept:
            end += "; geonav's fence stays on the autopilot"
        track = "" if self._draw is not None else f"; track {self.png_path}"
        steps = f"{self.steps} steps"
        if self.flown_steps is not None and self.flown_steps != self.steps:
            steps += f" ({self.flown_steps} flown)"
        return f"{head}; {steps}; {end}; record {self.record_path}{track}"


def exit_code_of(outcome: str, signal_name: str | None) -> int:
    """The process exit code of an outcome: 128 + the signal's number when one ended it."""
    if outcome == "interrupted" and signal_name:
        return 128 + int(signal.Signals[signal_name])
    return OUTCOMES[outcome]


#: How errors of an outcome begin their message ("link lost: no autopilot heartbeat").
_OUTCOME_PREFIXES = {
    "link_lost": ("link lost: ",),
    "takeover": ("operator took over: ", "operator takeover: "),
    "failsafe": ("autopilot failsafe: ",),
    "position_lost": ("position lost: ",),
    "interrupted": ("interrupted: ",),
}


def strip_outcome(outcome: str, text: str) -> str:
    """``text`` without a leading restatement of ``outcome`` (the summary says it once)."""
    for prefix in (OUTCOME_WORDS[outcome] + ": ",) + _OUTCOME_PREFIXES.get(outcome, ()):
        if text.lower().startswith(prefix):
            return text[len(prefix):]
    return text


def classify(err: FlightError, phase: str) -> str:
    """Outcome word of a flight error raised in ``phase``."""
    if isinstance(err, LinkLost):
        return "link_lost"
    if isinstance(err, PositionLost):
        return "position_lost"
    if isinstance(err, AutopilotFailsafe):
        return "failsafe"
    if isinstance(err, OperatorTakeover):
        return "takeover"
    if isinstance(err, PreflightRefused):
        return "refused"
    if isinstance(err, BatteryLow) and phase in ("preflight", "arming"):
        return "refused"
    if phase in ("preflight", "arming") and isinstance(err, (CommandRejected, FlightTimeout)):
        return "refused"
    if phase in ("preflight", "arming") and not isinstance(err, SafetyViolation):
        return "refused"
    return "safety_stop"
