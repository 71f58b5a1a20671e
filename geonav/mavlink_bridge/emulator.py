"""A MAVLink vehicle emulator for tests and dry runs (not a flight simulator).

It is a kinematic multicopter (a point mass under a second-order position
loop with speed and acceleration limits, so it overshoots and settles like a
real copter) that speaks MAVLink 2 through pymavlink over UDP or TCP on
127.0.0.1 and reproduces the autopilot behaviour the bridge relies on, as
documented by PX4 and ArduPilot and observed on ArduCopter SITL
(``shared/notes/mavlink.md``; issue 7):

* HEARTBEAT with the right ``autopilot``, ``type`` and ``custom_mode``
  encoding; ``system_status`` BOOT during a boot delay, then STANDBY
  (ACTIVE when armed); a mode change accepted during boot is undone when
  boot ends.
* Arming refused (``FAILED`` plus ``STATUSTEXT "PreArm: ..."``) until the
  vehicle is ready; GPS_GLOBAL_ORIGIN appears after a delay, and
  LOCAL_POSITION_NED only later.
* PX4 flavour: default telemetry streams; OFFBOARD (main mode 6) refused
  unless a setpoint stream is running; leaves OFFBOARD after
  ``COM_OF_LOSS_T`` without setpoints; auto-disarm ``COM_DISARM_PRFLT``
  after arming without take-off; takes off by a position setpoint.
* ArduPilot flavour: no telemetry streams on a new link (only HEARTBEAT and
  STATUSTEXT) until ``MAV_CMD_SET_MESSAGE_INTERVAL`` or
  ``REQUEST_DATA_STREAM``; position targets ignored outside GUIDED and on the
  ground; ``MAV_CMD_NAV_TAKEOFF`` (relative altitude) needed to leave the
  ground, within ``DISARM_DELAY`` of arming.
* COMMAND_ACK for every COMMAND_LONG/COMMAND_INT, AUTOPILOT_VERSION,
  HOME_POSITION, a minimal parameter protocol (what MAVSDK asks for).
* Battery (SYS_STATUS, BATTERY_STATUS) draining while armed, with each
  autopilot's low and critical warnings and an optional battery failsafe; the
  mission protocol for fence items, enforced with each autopilot's fence
  parameters (PX4 ``GF_ACTION``, ArduPilot ``FENCE_ENABLE``/``FENCE_ACTION``);
  PX4's STATUSTEXT only to a link that has a GCS or same-system onboard heartbeat;
  the HEARTBEAT's CRITICAL while a failsafe is active.
* Fault injection: link drop, arming refusal, GPS loss, operator mode change,
  battery drop, a gust.

Every delay is in emulated seconds and ``time_scale`` runs emulated time
faster than the wall clock, so tests can fly whole missions in seconds.
One thread per emulator (``start()`` is idempotent, ``stop()`` joins it)
polls a non-blocking socket every 10 ms and advances emulated time by the
wall time since the last iteration, but by at most ``max_dt_s``: a frozen
process (a garbage-collector pause, a loaded machine) pauses the vehicle, as
lockstep SITL does, instead of integrating the whole gap as one jump that
fires failsafe timers at once. The local NED frame is the autopilot's own
(:mod:`geonav.mavlink_bridge.frames`). Everything the emulator receives is
recorded for assertions.
"""

from __future__ import annotations

import collections
import logging
import math
import socket
import threading
import time
from typing import Any

import numpy as np

from geonav.errors import FlightError
from geonav.geo import LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge._mav import mavlink2
from geonav.mavlink_bridge.emulator_config import (
    TICK_WALL_S,
    EmulatorConfig,
    ReceivedCommand,
    ReceivedSetpoint,
)
from geonav.mavlink_bridge.emulator_handlers import HandlersMixin
from geonav.mavlink_bridge.emulator_link import LinkMixin, Peer
from geonav.mavlink_bridge.emulator_messages import MessagesMixin
from geonav.mavlink_bridge.emulator_physics import PhysicsMixin
from geonav.mavlink_bridge.emulator_safety import SafetyMixin
from geonav.mavlink_bridge.frames import LocalFrame

log = logging.getLogger(__name__)

__all__ = ["Emulator", "EmulatorConfig", "ReceivedCommand", "ReceivedSetpoint", "run_standalone"]


class Emulator(HandlersMixin, SafetyMixin, MessagesMixin, PhysicsMixin, LinkMixin):
    """The emulated vehicle; runs in its own thread. Use as a context manager.

    Args:
        config: the vehicle's settings.
    """

    def __init__(self, config: EmulatorConfig | None = None) -> None:
        self.cfg = config or EmulatorConfig()
        self.flavour = self.cfg.autopilot
        self._mav = mavlink2.MAVLink(None, srcSystem=self.cfg.system_id, srcComponent=1)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._peers: dict[Any, Peer] = {}
        self._udp: socket.socket | None = None
        self._tcp_listen: socket.socket | None = None
        self._udpout_addr: tuple[str, int] | None = None
        self.port = 0
        # Records for assertions.
        self.setpoints: list[ReceivedSetpoint] = []
        self.commands: list[ReceivedCommand] = []
        self.events: list[tuple[float, str]] = []
        self.track: list[tuple[float, float, float, float]] = []
        self.peer_heartbeats = 0
        #: loop iterations run, and (wall gap s, emulated dt s) of the last ones.
        self.iterations = 0
        self.steps_log: collections.deque[tuple[float, float]] = collections.deque(maxlen=2000)
        # Vehicle state.
        self.t_s = 0.0
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.target: np.ndarray | None = None
        self.armed = False
        self.landed = True
        self.mode = "posctl" if self.flavour == M.PX4 else "stabilize"
        self._boot_mode: str | None = self.mode
        self.origin: LonLat | None = None
        self.home = self.cfg.home
        self._armed_at: float | None = None
        self._took_off = False
        self._touchdown_at: float | None = None
        self._last_sp_t: float = -1e9
        self._sp_stream_start: float = -1e9
        self._intervals: dict[str, float] = {}
        self._next_due: dict[str, float] = {}
        self._rtl_phase = ""
        # Faults.
        self._link_down_until = 0.0
        self._refuse_arming: str | None = None
        self._preflight_text_t = -math.inf
        self._gps_lost = False
        self._param_overrides: dict[str, float] = {}
        self._pending_reply: str | None = None
        self._frame: LocalFrame | None = None
        self._closed = False
        # Battery, failsafes, the uploaded fence, what the autopilot said.
        self.battery = float(self.cfg.battery_pct)
        self.failsafe = ""
        self.fence_items: list[Any] = []
        self.fence_breached = False
        self.texts: list[tuple[float, int, str, bool]] = []
        """(t, severity, text, sent) of every STATUSTEXT (sent False: the PX4 gate held it)."""
        self.peer_heartbeat_ids: dict[tuple[int, int, int], float] = {}
        """(system, component, MAV_TYPE) of every heartbeat heard -> when it was last heard."""
        self._battery_warned = 0
        self._gps_lost_at: float | None = None
        self._upload: dict[str, Any] | None = None
        self._setup_streams()
        self._open_transport()
        if self.cfg.airborne_alt_m > 0:
            self._start_airborne(self.cfg.airborne_alt_m)

    def start(self) -> Emulator:
        """Start the emulator thread (once: a second call does nothing); returns self."""
        with self._lock:
            if self._closed:
                raise FlightError("emulator was stopped; make a new one")
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name="mavlink-emulator", daemon=True
                )
                self._thread.start()
        return self

    @property
    def running(self) -> bool:
        """Whether the emulator thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def stop(self) -> None:
        """Stop the thread, wait for it, and close the sockets (safe to call twice)."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            socks = [self._udp, self._tcp_listen] + [p.sock for p in self._peers.values()]
        for sock in socks:
            if sock is not None:
                sock.close()

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def drop_link(self, duration_s: float | None = None) -> None:
        """Drop the link both ways for ``duration_s`` wall seconds (None: for good)."""
        with self._lock:
            until = math.inf if duration_s is None else time.monotonic() + duration_s
            self._link_down_until = until
            self._event("fault: link dropped")

    def refuse_arming(self, reason: str | None = "Fault injected") -> None:
        """Refuse every arming request with ``PreArm: reason`` (None lifts it)."""
        with self._lock:
            self._refuse_arming = reason

    def lose_gps(self) -> None:
        """Lose GPS: no fix and no position estimate at once (the position streams stop);
        in the air the autopilot's EKF failsafe lands ``gps_failsafe_s`` later."""
        with self._lock:
            self._gps_lost = True
            self._gps_lost_at = self.t_s
            self._event("fault: GPS lost")

    def say(self, severity: int, text: str) -> None:
        """The autopilot sends a STATUSTEXT (through PX4's gate, as its own would)."""
        with self._lock:
            self._statustext(severity, text)

    def drain_battery(self, to_pct: float) -> None:
        """The battery drops to ``to_pct`` at once (warnings and failsafe follow)."""
        with self._lock:
            self.battery = float(to_pct)
            self._event(f"fault: battery at {to_pct:g}%")

    def operator_mode(self, name: str) -> None:
        """Change the mode as an RC pilot would (``hold`` is LOITER on ArduPilot)."""
        with self._lock:
            number = M.custom_mode_value(self.flavour, name)
            self._set_mode(M.decode_mode(self.flavour, number), why="operator")

    def push(self, north_m: float, east_m: float) -> None:
        """A gust blows the vehicle this far at once (fence-overshoot tests)."""
        with self._lock:
            self.pos[0] += north_m
            self.pos[1] += east_m
            self._event(f"fault: gust moved the vehicle {north_m:+.1f} m N {east_m:+.1f} m E")

    def _start_airborne(self, alt_m: float) -> None:
        self.armed = True
        self.landed = False
        self._took_off = True
        self._armed_at = 0.0
        self.pos = np.array([0.0, 0.0, -alt_m])
        self.mode = M.decode_mode(self.flavour, M.custom_mode_value(self.flavour, "hold"))
        self._boot_mode = None
        self.target = self.pos.copy()

    def used_setpoints(self) -> list[ReceivedSetpoint]:
        """Setpoints the vehicle acted on."""
        with self._lock:
            return [s for s in self.setpoints if s.used]

    def commands_named(self, command: int) -> list[ReceivedCommand]:
        """Received commands with this MAV_CMD id."""
        with self._lock:
            return [c for c in self.commands if c.command == command]

    def mode_history(self) -> list[str]:
        """Mode-change events in order."""
        with self._lock:
            return [e for _, e in self.events if e.startswith("mode ")]

    def _run(self) -> None:
        # Emulated time per iteration is bounded: a frozen process pauses the vehicle.
        max_dt = max(self.cfg.max_dt_s, 2.0 * TICK_WALL_S * self.cfg.time_scale)
        last = time.monotonic()
        while not self._stop.is_set():
            try:
                self._poll_io(TICK_WALL_S)
                now = time.monotonic()
                gap = now - last
                dt = min(gap * self.cfg.time_scale, max_dt)
                last = now
                with self._lock:
                    self.t_s += dt
                    self._step(dt)
                    self._send_due()
                    self.iterations += 1
                    self.steps_log.append((gap, dt))
            except Exception:  # the emulated vehicle must not die of one bad iteration
                log.exception("emulator iteration failed")
                time.sleep(TICK_WALL_S)


def run_standalone(config: EmulatorConfig, stop: threading.Event, on_ready: Any = None) -> None:
    """Run an emulator until ``stop`` is set (used by ``geonav mavlink emulate``)."""
    emu = Emulator(config).start()
    if on_ready is not None:
        on_ready(emu)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        emu.stop()
