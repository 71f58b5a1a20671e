"""The setpoint pump: streams the current target at 10-20 Hz while the policy loop lives.

PX4 needs a setpoint stream (> 2 Hz) before and during OFFBOARD and fails
over after ``COM_OF_LOSS_T`` without one; a resender that outlives the logic
defeats that failsafe (MAVSDK-Python#374). So the pump sends only while the
flight loop keeps calling :meth:`SetpointPump.tick`; when the last tick is
older than ``deadline_s`` it stops sending, stops any backend resender and
commands LAND. It also runs the watchdogs every cycle and stops on the first
fault without commanding anything (the flight loop decides), and it refuses
any target outside the geofence, so such a target is never sent. Nothing
kills the pump silently: an exception in a send (MAVSDK raises after 1 s
without an answer) is recorded as a :class:`PumpFault` that the flight loop
sees within one cycle (:meth:`SetpointPump.raise_if_fault`) and ends in
LAND/RTL.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from geonav.errors import FlightError
from geonav.geo import LocalNED
from geonav.mavlink_bridge.safety import PumpFault, Watchdog
from geonav.mavlink_bridge.vehicle import Vehicle

log = logging.getLogger(__name__)


class SetpointPump:
    """Streams one NED target to a vehicle from a thread.

    Args:
        vehicle: the link.
        rate_hz: send rate (10-20 Hz).
        deadline_s: stop and LAND when the flight loop has not ticked for this long.
        fence_check: raises SafetyViolation for a target outside the fence.
        watchdog: link/mode watchdog run every cycle (None: none).
        land_timeout_s: ACK timeout of the LAND command after a stall.
    """

    def __init__(
        self,
        vehicle: Vehicle,
        *,
        rate_hz: float = 15.0,
        deadline_s: float = 2.0,
        fence_check: Callable[[LocalNED], None] | None = None,
        watchdog: Watchdog | None = None,
        land_timeout_s: float = 5.0,
    ) -> None:
        if not 2.0 < rate_hz <= 50.0:
            raise FlightError(f"setpoint rate {rate_hz} Hz: PX4 needs > 2 Hz; use 10-20 Hz")
        self.vehicle = vehicle
        self.rate_hz = rate_hz
        self.deadline_s = deadline_s
        self.fence_check = fence_check
        self.watchdog = watchdog
        self.land_timeout_s = land_timeout_s
        self.fault: str | None = None
        self.fault_error: FlightError | None = None
        self.landed_by_pump = False
        self.sent = 0
        self._target: LocalNED | None = None
        self._yaw_deg = 0.0
        self._last_tick = time.monotonic()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def target(self) -> LocalNED | None:
        """The target being streamed."""
        return self._target

    @property
    def running(self) -> bool:
        """Whether the pump thread is streaming."""
        return self._thread is not None and self._thread.is_alive()

    def set_target(self, target: LocalNED, yaw_deg: float) -> None:
        """Replace the streamed target (checked against the fence first) and tick.

        Raises:
            SafetyViolation: the target is outside the fence; nothing is sent.
            PumpFault (or the watchdog's error): the pump already stopped on a fault.
        """
        self.raise_if_fault()
        if self.fence_check is not None:
            self.fence_check(target)
        with self._lock:
            self._target = target
            self._yaw_deg = yaw_deg
        self.tick()
        if self.running:
            try:
                self.vehicle.send_position_target(target, yaw_deg)
            except Exception as err:  # a send that raises is a fault, never silent
                self._fail(PumpFault(f"setpoint send failed: {type(err).__name__}: {err}"))
                self.raise_if_fault()
            self.sent += 1

    def tick(self) -> None:
        """Proof of life from the flight loop."""
        self._last_tick = time.monotonic()

    def start(self) -> None:
        """Start streaming (a target must be set)."""
        if self._target is None:
            raise FlightError("setpoint pump started without a target")
        if self.running:
            return
        self._stop.clear()
        self.tick()
        self._thread = threading.Thread(target=self._run, name="setpoint-pump", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop streaming (and any backend resender)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        self._stop_backend()

    def _fail(self, err: FlightError) -> None:
        if self.fault_error is None:
            self.fault_error = err
            self.fault = str(err)
            log.info("setpoint pump stopped: %s", err)
        self._stop.set()
        self._stop_backend()

    def _run(self) -> None:
        try:
            self._loop()
        except Exception as err:  # the pump thread never dies silently
            self._fail(PumpFault(f"setpoint pump failed: {type(err).__name__}: {err}"))

    def _loop(self) -> None:
        period = 1.0 / self.rate_hz
        while not self._stop.is_set():
            started = time.monotonic()
            stalled_s = started - self._last_tick
            if stalled_s > self.deadline_s:
                self._fail(
                    PumpFault(
                        f"policy loop stalled: no tick for {stalled_s:.1f} s "
                        f"(deadline {self.deadline_s:.1f} s); stopped setpoints, commanding LAND"
                    )
                )
                try:
                    self.vehicle.land(self.land_timeout_s)
                    self.landed_by_pump = True
                except FlightError as err:
                    log.error("LAND after policy stall failed: %s", err)
                return
            if self.watchdog is not None:
                fault: FlightError | None
                try:
                    fault = self.watchdog.error(self.vehicle.state())
                except FlightError as state_err:
                    fault = state_err
                if fault is not None:
                    self._fail(fault)
                    return
            with self._lock:
                target, yaw = self._target, self._yaw_deg
            if target is not None:
                try:
                    self.vehicle.send_position_target(target, yaw)
                except Exception as err:
                    self._fail(PumpFault(f"setpoint send failed: {type(err).__name__}: {err}"))
                    return
                self.sent += 1
            self._stop.wait(max(0.0, period - (time.monotonic() - started)))

    def _stop_backend(self) -> None:
        try:
            self.vehicle.stop_setpoints()
        except Exception as err:  # noqa: BLE001 - stopping must never raise
            log.warning("stopping the backend's setpoint stream: %s", err)

    def raise_if_fault(self) -> None:
        """Raise the pump's fault (typed: LinkLost, OperatorTakeover, PumpFault, ...)."""
        if self.fault_error is not None:
            raise type(self.fault_error)(str(self.fault_error))
