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
* Fault injection: link drop, arming refusal, GPS loss, operator mode change.

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
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from geonav.errors import FlightError
from geonav.geo import LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge._mav import mavlink2
from geonav.mavlink_bridge.frames import LocalFrame, local_frame

log = logging.getLogger(__name__)

_TICK_WALL_S = 0.01


@dataclass
class EmulatorConfig:
    """Settings of the emulated vehicle. Times are emulated seconds.

    Attributes:
        autopilot: ``"px4"`` or ``"ardupilot"``.
        home: home position (also the EKF origin when ``gps`` is true).
        listen: where to listen: ``udp:127.0.0.1:PORT`` (replies to every
            peer that sent a packet), ``tcp:127.0.0.1:PORT`` (server), or
            ``udpout:HOST:PORT`` (send there first, as PX4 SITL does to
            14540). Port 0 picks a free port (see ``Emulator.port``).
        system_id: MAVLink system id of the vehicle (component id is 1).
        time_scale: emulated seconds per wall second.
        boot_s: time in MAV_STATE_BOOT.
        prearm_s: arming fails with a PreArm STATUSTEXT before this time.
        origin_s: time at which the EKF origin (GPS_GLOBAL_ORIGIN) is set.
        local_position_s: time from which LOCAL_POSITION_NED is valid.
        gps: whether the vehicle sets its EKF origin from GPS; if false the
            origin must come from SET_GPS_GLOBAL_ORIGIN.
        max_speed_mps: horizontal speed limit.
        max_climb_mps: vertical speed limit.
        max_accel_mps2: acceleration limit (per axis group).
        natural_freq_hz: natural frequency of the position loop.
        damping: damping ratio of the position loop (< 1 overshoots).
        offboard_loss_s: PX4 COM_OF_LOSS_T.
        offboard_loss_action: mode PX4 takes after offboard loss
            (COM_OBL_RC_ACT; ``"land"`` or ``"hold"``).
        disarm_delay_s: auto-disarm when armed on the ground without taking
            off (PX4 COM_DISARM_PRFLT, ArduPilot DISARM_DELAY).
        land_disarm_s: disarm this long after touching down.
        land_speed_mps: descent speed in LAND/RTL.
        rtl_alt_m: RTL return altitude above home (ArduPilot RTL_ALT).
        position_rate_hz: default rate of position messages (PX4 flavour).
        max_dt_s: most emulated seconds one loop iteration may advance (at
            least two 10 ms ticks at ``time_scale``), so a process freeze
            pauses the vehicle instead of jumping it.
        airborne_alt_m: start already armed and hovering this high above
            home in the hold mode (a vehicle someone else is flying); 0: on the ground.
        preflight_fail: PX4 only: a pre-flight check that keeps failing with
            this text (the HEARTBEAT then shows UNINIT, not STANDBY, and the
            text is repeated every 5 s, as PX4 SIH did after a landing with
            "Preflight: GPS Vertical Pos Drift too high"); "" for none.
    """

    autopilot: str = M.PX4
    home: LonLat = field(default_factory=lambda: LonLat(4.4777, 51.9244, 0.0))
    listen: str = "udp:127.0.0.1:0"
    system_id: int = 1
    time_scale: float = 1.0
    boot_s: float = 2.0
    prearm_s: float = 5.0
    origin_s: float = 3.0
    local_position_s: float = 4.0
    gps: bool = True
    max_speed_mps: float = 5.0
    max_climb_mps: float = 3.0
    max_accel_mps2: float = 4.0
    natural_freq_hz: float = 0.35
    damping: float = 0.6
    offboard_loss_s: float = 1.0
    offboard_loss_action: str = "land"
    disarm_delay_s: float = 10.0
    land_disarm_s: float = 1.0
    land_speed_mps: float = 1.5
    rtl_alt_m: float = 15.0
    position_rate_hz: float = 10.0
    max_dt_s: float = 0.1
    airborne_alt_m: float = 0.0
    preflight_fail: str = ""

    def __post_init__(self) -> None:
        if self.autopilot not in (M.PX4, M.ARDUPILOT):
            raise FlightError(f"emulator autopilot {self.autopilot!r}: use 'px4' or 'ardupilot'")
        if self.time_scale <= 0:
            raise FlightError(f"time_scale {self.time_scale} must be > 0")


@dataclass(frozen=True)
class ReceivedSetpoint:
    """A SET_POSITION_TARGET_LOCAL_NED as the emulator received it."""

    t_s: float
    coordinate_frame: int
    type_mask: int
    north_m: float
    east_m: float
    down_m: float
    yaw_deg: float
    mode: str
    used: bool


@dataclass(frozen=True)
class ReceivedCommand:
    """A COMMAND_LONG / COMMAND_INT and the result the emulator answered."""

    t_s: float
    command: int
    params: tuple[float, ...]
    result: int
    source: tuple[int, int] = (0, 0)


class _Peer:
    def __init__(self, addr: Any, sock: socket.socket | None = None) -> None:
        self.addr = addr
        self.sock = sock
        self.parser = mavlink2.MAVLink(None, srcSystem=0, srcComponent=0)
        self.parser.robust_parsing = True


class Emulator:
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
        self._peers: dict[Any, _Peer] = {}
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
        self._setup_streams()
        self._open_transport()
        if self.cfg.airborne_alt_m > 0:
            self._start_airborne(self.cfg.airborne_alt_m)

    # ------------------------------------------------------------------ setup
    def _setup_streams(self) -> None:
        if self.flavour == M.PX4:
            pos = 1.0 / self.cfg.position_rate_hz
            self._intervals = {
                "LOCAL_POSITION_NED": pos,
                "GLOBAL_POSITION_INT": pos,
                "SYS_STATUS": 1.0,
                "EXTENDED_SYS_STATE": 1.0,
                "HOME_POSITION": 2.0,
                "ATTITUDE": pos,
                "GPS_RAW_INT": 1.0,
            }
        else:
            # ArduCopter: every SRn_* default stream rate is 0.
            self._intervals = {}

    def _open_transport(self) -> None:
        kind, _, rest = self.cfg.listen.partition(":")
        host, _, port_s = rest.rpartition(":")
        try:
            port = int(port_s)
        except ValueError as err:
            raise FlightError(f"emulator listen address {self.cfg.listen!r} has no port") from err
        if not 0 <= port <= 65535:
            raise FlightError(f"emulator listen address {self.cfg.listen!r}: port {port} is "
                              "not a port (0..65535; 0 picks a free one)")
        host = host or "127.0.0.1"
        if kind == "udp":
            self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._udp.bind((host, port))
            self._udp.setblocking(False)
            self.port = self._udp.getsockname()[1]
        elif kind == "udpout":
            self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._udp.bind(("127.0.0.1", 0))
            self._udp.setblocking(False)
            self._udpout_addr = (host, port)
            self._peers[self._udpout_addr] = _Peer(self._udpout_addr)
            self.port = port
        elif kind == "tcp":
            self._tcp_listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._tcp_listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._tcp_listen.bind((host, port))
            self._tcp_listen.listen(4)
            self._tcp_listen.setblocking(False)
            self.port = self._tcp_listen.getsockname()[1]
        else:
            raise FlightError(f"emulator listen {self.cfg.listen!r}: use udp:, udpout: or tcp:")

    @property
    def connect_url(self) -> str:
        """The pymavlink connection string a client uses to reach this emulator."""
        if self._tcp_listen is not None:
            return f"tcp:127.0.0.1:{self.port}"
        if self._udpout_addr is not None:
            return f"udpin:{self._udpout_addr[0]}:{self._udpout_addr[1]}"
        return f"udpout:127.0.0.1:{self.port}"

    @property
    def mavsdk_url(self) -> str:
        """The MAVSDK connection URL for this emulator."""
        if self._tcp_listen is not None:
            return f"tcpout://127.0.0.1:{self.port}"
        if self._udpout_addr is not None:
            return f"udpin://{self._udpout_addr[0]}:{self._udpout_addr[1]}"
        return f"udpout://127.0.0.1:{self.port}"

    # -------------------------------------------------------------- lifecycle
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

    # --------------------------------------------------------- fault injection
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
        """Lose the position estimate: position streams stop, an airborne vehicle lands."""
        with self._lock:
            self._gps_lost = True
            self._event("fault: GPS lost")
            self._statustext(3, "EKF: position estimate lost")
            if not self.landed:
                self._set_mode("land", why="failsafe: no position")

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

    # ------------------------------------------------------------ record views
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

    # -------------------------------------------------------------- main loop
    def _run(self) -> None:
        # Emulated time per iteration is bounded: a frozen process pauses the vehicle.
        max_dt = max(self.cfg.max_dt_s, 2.0 * _TICK_WALL_S * self.cfg.time_scale)
        last = time.monotonic()
        while not self._stop.is_set():
            try:
                self._poll_io(_TICK_WALL_S)
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
                time.sleep(_TICK_WALL_S)

    def _link_up(self) -> bool:
        return time.monotonic() >= self._link_down_until

    def _poll_io(self, timeout_s: float) -> None:
        socks = [s for s in [self._udp, self._tcp_listen] if s is not None]
        socks += [p.sock for p in self._peers.values() if p.sock is not None]
        try:
            ready, _, _ = select.select(socks, [], [], timeout_s)
        except (OSError, ValueError):
            return
        for sock in ready:
            if sock is self._tcp_listen:
                try:
                    conn, addr = sock.accept()
                except OSError:
                    continue
                conn.setblocking(False)
                self._peers[addr] = _Peer(addr, conn)
                continue
            if sock is self._udp:
                # Drain every datagram that is ready (non-blocking socket).
                while True:
                    try:
                        data, addr = sock.recvfrom(65535)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        break
                    self._received(data, addr)
                continue
            addr = next((a for a, p in self._peers.items() if p.sock is sock), None)
            if addr is None:
                continue
            try:
                data = sock.recv(65535)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                self._drop_peer(addr)
                continue
            if not data:
                self._drop_peer(addr)
                continue
            self._received(data, addr)

    def _received(self, data: bytes, addr: Any) -> None:
        if not self._link_up():
            return
        peer = self._peers.get(addr)
        if peer is None:
            peer = self._peers[addr] = _Peer(addr)
        try:
            msgs = peer.parser.parse_buffer(data) or []
        except mavlink2.MAVError as err:
            log.debug("emulator: bad packet from %s: %s", addr, err)
            return
        with self._lock:
            for msg in msgs:
                try:
                    self._handle(msg)
                except (ValueError, TypeError, ArithmeticError, KeyError) as err:
                    # A malformed request must not kill the emulated vehicle.
                    log.warning("emulator: cannot handle %s: %s", msg.get_type(), err)

    def _drop_peer(self, addr: Any) -> None:
        peer = self._peers.pop(addr, None)
        if peer is not None and peer.sock is not None:
            peer.sock.close()

    def _send(self, msg: Any) -> None:
        if not self._link_up() or not self._peers:
            return
        buf = msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        for addr, peer in list(self._peers.items()):
            try:
                if peer.sock is not None:
                    peer.sock.sendall(buf)
                elif self._udp is not None:
                    self._udp.sendto(buf, addr)
            except (BlockingIOError, ConnectionError, OSError):
                if peer.sock is not None:
                    self._drop_peer(addr)

    # ------------------------------------------------------------------ state
    def _event(self, text: str) -> None:
        self.events.append((self.t_s, text))
        log.debug("emulator t=%.2f: %s", self.t_s, text)

    def _statustext(self, severity: int, text: str) -> None:
        self._send(self._mav.statustext_encode(severity, text.encode()[:50]))

    @property
    def booted(self) -> bool:
        """Whether the boot delay is over."""
        return self.t_s >= self.cfg.boot_s

    def _position_valid(self) -> bool:
        return (
            self.origin is not None and not self._gps_lost and self.t_s >= self.cfg.local_position_s
        )

    def _set_mode(self, name: str, why: str = "") -> None:
        if name != self.mode:
            self.mode = name
            self._event(f"mode {name}" + (f" ({why})" if why else ""))
        if name in ("land", "rtl", "hold", "loiter", "posctl", "stabilize", "brake", "althold"):
            # Leaving autonomy: hold (or land) where the vehicle is now.
            self.target = self.pos.copy() if not self.landed else None
            self._rtl_phase = "return" if name == "rtl" else ""

    def _disarm(self, why: str) -> None:
        if self.armed:
            self.armed = False
            self._armed_at = None
            self._took_off = False
            self._touchdown_at = None
            self.target = None
            self._event(f"disarmed ({why})")

    def _step(self, dt: float) -> None:
        cfg = self.cfg
        # Boot end: a mode set during boot is undone.
        if self.booted and self._boot_mode is not None:
            if self.mode != self._boot_mode:
                self._event(f"mode {self._boot_mode} (boot finished, mode reset)")
                self.mode = self._boot_mode
            self._boot_mode = None
        if self.origin is None and cfg.gps and self.t_s >= cfg.origin_s and not self._gps_lost:
            self._set_origin(self.home, source="GPS")
        # PX4 offboard loss.
        if self.flavour == M.PX4 and self.mode == "offboard":
            if self.t_s - self._last_sp_t > cfg.offboard_loss_s:
                self._statustext(4, "Failsafe: offboard control lost")
                self._set_mode(cfg.offboard_loss_action, why="offboard loss")
        # Auto-disarm before take-off.
        if self.armed and not self._took_off and self._armed_at is not None:
            if self.t_s - self._armed_at > cfg.disarm_delay_s:
                self._statustext(4, "Disarmed: no takeoff")
                self._disarm("auto-disarm, no take-off")
        self._control(dt)
        self.track.append((self.t_s, float(self.pos[0]), float(self.pos[1]), float(self.pos[2])))
        if len(self.track) > 200_000:
            del self.track[:100_000]

    def _goal(self) -> np.ndarray | None:
        """Position the controller steers to now, by mode."""
        if not self.armed:
            return None
        if self.mode == "land":
            goal = self.target.copy() if self.target is not None else self.pos.copy()
            goal[2] = self.pos[2] + 5.0  # descend at the land speed limit
            return goal
        if self.mode == "rtl":
            return None  # handled in _control
        return self.target

    def _control(self, dt: float) -> None:
        cfg = self.cfg
        if not self.armed:
            self.vel[:] = 0.0
            return
        vz_limit = cfg.max_climb_mps
        goal = self._goal()
        if self.mode == "rtl":
            home = np.array([0.0, 0.0, 0.0]) if self.origin is None else self._home_ned()
            if self._rtl_phase == "return":
                goal = np.array([home[0], home[1], min(self.pos[2], -cfg.rtl_alt_m)])
                if np.hypot(*(self.pos[:2] - home[:2])) < 0.5 and np.linalg.norm(self.vel) < 0.5:
                    self._rtl_phase = "land"
            if self._rtl_phase == "land":
                goal = np.array([home[0], home[1], self.pos[2] + 5.0])
        if self.mode in ("land", "rtl") and goal is not None and goal[2] > self.pos[2]:
            vz_limit = cfg.land_speed_mps
            if self.target is None:
                self.target = self.pos.copy()
        if goal is None:
            goal = self.pos.copy() if not self.landed else None
        if goal is None:
            self.vel[:] = 0.0
            return
        if self.landed and goal[2] >= self.pos[2] - 0.05:
            # On the ground and not asked to climb.
            self.vel[:] = 0.0
            self._maybe_auto_disarm_landed()
            return
        wn = 2 * math.pi * cfg.natural_freq_hz
        acc = wn * wn * (goal - self.pos) - 2 * cfg.damping * wn * self.vel
        # Limits: horizontal acceleration norm, vertical acceleration, speeds.
        ah = np.hypot(acc[0], acc[1])
        if ah > cfg.max_accel_mps2:
            acc[:2] *= cfg.max_accel_mps2 / ah
        acc[2] = float(np.clip(acc[2], -cfg.max_accel_mps2, cfg.max_accel_mps2))
        self.vel += acc * dt
        vh = np.hypot(self.vel[0], self.vel[1])
        if vh > cfg.max_speed_mps:
            self.vel[:2] *= cfg.max_speed_mps / vh
        self.vel[2] = float(np.clip(self.vel[2], -cfg.max_climb_mps, vz_limit))
        self.pos += self.vel * dt
        if self.pos[2] < -0.3 and self.landed:
            self.landed = False
            self._took_off = True
            self._touchdown_at = None
            self._event("airborne")
        if self.pos[2] >= 0.0:
            self.pos[2] = 0.0
            self.vel[2] = min(self.vel[2], 0.0)
            if not self.landed and self.vel[2] >= -0.01 and goal[2] >= 0.0:
                self.landed = True
                self.vel[:] = 0.0
                self._touchdown_at = self.t_s
                self._event("landed")
        if self.landed:
            self._maybe_auto_disarm_landed()

    def _maybe_auto_disarm_landed(self) -> None:
        if (
            self._touchdown_at is not None
            and self.t_s - self._touchdown_at > self.cfg.land_disarm_s
        ):
            self._disarm("landed")

    def _home_ned(self) -> np.ndarray:
        if self.origin is None:
            return np.zeros(3)
        n, e = self._to_ned(self.home)
        return np.array([n, e, 0.0])

    # ------------------------------------------------------------- geography
    def _set_origin(self, origin: LonLat, source: str) -> None:
        self.origin = origin
        # The autopilot's own lon/lat <-> NED formula (ArduPilot flat earth, PX4 aeqd).
        self._frame = local_frame(self.flavour, origin)
        self._event(f"EKF origin set from {source}: {origin}")
        self._send_origin()
        self._send_home()

    def _to_ned(self, q: LonLat) -> tuple[float, float]:
        assert self._frame is not None
        return self._frame.to_ne(q)

    def lonlat_of(self, north_m: float, east_m: float, down_m: float = 0.0) -> LonLat:
        """WGS 84 position of a point of the local NED frame (the autopilot's formula)."""
        if self.origin is None or self._frame is None:
            raise FlightError("emulator EKF origin not set yet")
        lon, lat = self._frame.to_lonlat(float(north_m), float(east_m))
        return LonLat(lon, lat, self.origin.alt_m - float(down_m))

    # ------------------------------------------------------------- telemetry
    def _time_boot_ms(self) -> int:
        return int(self.t_s * 1000) & 0xFFFFFFFF

    def _heartbeat(self) -> Any:
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            M.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
        )
        if not self.booted:
            status = M.MAV_STATE_BOOT
        elif self.armed:
            status = M.MAV_STATE_ACTIVE
        elif self.flavour == M.PX4 and self.cfg.preflight_fail:
            # PX4's HEARTBEAT.hpp: STANDBY only while pre_flight_checks_pass, else UNINIT.
            status = M.MAV_STATE_UNINIT
            if self.t_s - self._preflight_text_t >= 5.0:
                self._preflight_text_t = self.t_s
                self._statustext(4, self.cfg.preflight_fail)
        else:
            status = M.MAV_STATE_STANDBY
        autopilot = M.MAV_AUTOPILOT_PX4 if self.flavour == M.PX4 else M.MAV_AUTOPILOT_ARDUPILOTMEGA
        custom = M.custom_mode_value(self.flavour, self.mode)
        return self._mav.heartbeat_encode(M.MAV_TYPE_QUADROTOR, autopilot, base, custom, status, 3)

    def _build(self, name: str) -> Any | None:
        mav = self._mav
        if name == "LOCAL_POSITION_NED":
            if not self._position_valid():
                return None
            p, v = self.pos, self.vel
            return mav.local_position_ned_encode(
                self._time_boot_ms(), p[0], p[1], p[2], v[0], v[1], v[2]
            )
        if name == "GLOBAL_POSITION_INT":
            if not self._position_valid():
                return None
            q = self.lonlat_of(self.pos[0], self.pos[1], self.pos[2])
            return mav.global_position_int_encode(
                self._time_boot_ms(),
                int(q.lat_deg * 1e7),
                int(q.lon_deg * 1e7),
                int(q.alt_m * 1000),
                int(-self.pos[2] * 1000),
                int(self.vel[0] * 100),
                int(self.vel[1] * 100),
                int(self.vel[2] * 100),
                0,
            )
        if name == "HOME_POSITION":
            if self.origin is None:
                return None
            h = self._home_ned()
            q = self.home
            return mav.home_position_encode(
                int(q.lat_deg * 1e7),
                int(q.lon_deg * 1e7),
                int(q.alt_m * 1000),
                h[0],
                h[1],
                h[2],
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
            )
        if name == "GPS_GLOBAL_ORIGIN":
            if self.origin is None:
                return None
            o = self.origin
            return mav.gps_global_origin_encode(
                int(o.lat_deg * 1e7), int(o.lon_deg * 1e7), int(o.alt_m * 1000)
            )
        if name == "SYS_STATUS":
            sensors = 0x3F | (0x20 if self._position_valid() else 0)
            return mav.sys_status_encode(
                sensors, sensors, sensors, 100, 16000, 500, 90, 0, 0, 0, 0, 0, 0
            )
        if name == "EXTENDED_SYS_STATE":
            if self.landed:
                state = M.MAV_LANDED_STATE_ON_GROUND
            elif self.mode == "land" or (self.mode == "rtl" and self._rtl_phase == "land"):
                state = M.MAV_LANDED_STATE_LANDING
            else:
                state = M.MAV_LANDED_STATE_IN_AIR
            return mav.extended_sys_state_encode(0, state)
        if name == "ATTITUDE":
            return mav.attitude_encode(self._time_boot_ms(), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if name == "GPS_RAW_INT":
            q = self.home if self.origin is None else self.lonlat_of(*self.pos)
            fix = 0 if self._gps_lost or self.t_s < self.cfg.origin_s else 3
            return mav.gps_raw_int_encode(
                int(self.t_s * 1e6),
                fix,
                int(q.lat_deg * 1e7),
                int(q.lon_deg * 1e7),
                int(q.alt_m * 1000),
                80,
                120,
                0,
                0,
                12 if fix else 0,
            )
        if name == "POSITION_TARGET_LOCAL_NED":
            if self.target is None:
                return None
            t = self.target
            return mav.position_target_local_ned_encode(
                self._time_boot_ms(),
                M.MAV_FRAME_LOCAL_NED,
                M.TYPE_MASK_POSITION_YAW,
                t[0],
                t[1],
                t[2],
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            )
        if name == "AUTOPILOT_VERSION":
            caps = (
                mavlink2.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink2.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mavlink2.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink2.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mavlink2.MAV_PROTOCOL_CAPABILITY_MISSION_INT
            )
            version = (1 << 24) | (15 << 16) if self.flavour == M.PX4 else (4 << 24) | (7 << 16)
            return mav.autopilot_version_encode(
                caps,
                version | 0xFF,
                0,
                0,
                0,
                [0] * 8,
                [0] * 8,
                [0] * 8,
                0,
                0,
                0x47454F4E4156 + self.cfg.system_id,
            )
        if name == "HEARTBEAT":
            return self._heartbeat()
        return None

    def _send_origin(self) -> None:
        msg = self._build("GPS_GLOBAL_ORIGIN")
        if msg is not None:
            self._send(msg)

    def _send_home(self) -> None:
        msg = self._build("HOME_POSITION")
        if msg is not None:
            self._send(msg)

    def _send_due(self) -> None:
        due = dict(self._intervals)
        due["HEARTBEAT"] = 1.0
        for name, interval in due.items():
            if interval <= 0:
                continue
            if self.t_s >= self._next_due.get(name, 0.0):
                self._next_due[name] = self.t_s + interval
                msg = self._build(name)
                if msg is not None:
                    self._send(msg)

    # -------------------------------------------------------------- handlers
    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self.peer_heartbeats += 1
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if msg.target_system not in (0, self.cfg.system_id):
                return
            if msg.target_component not in (0, 1):
                return
            if kind == "COMMAND_LONG":
                params = (
                    msg.param1,
                    msg.param2,
                    msg.param3,
                    msg.param4,
                    msg.param5,
                    msg.param6,
                    msg.param7,
                )
            else:
                params = (
                    msg.param1,
                    msg.param2,
                    msg.param3,
                    msg.param4,
                    float(msg.x),
                    float(msg.y),
                    msg.z,
                )
            result = self._command(msg.command, params)
            self.commands.append(
                ReceivedCommand(
                    self.t_s,
                    msg.command,
                    params,
                    result,
                    (msg.get_srcSystem(), msg.get_srcComponent()),
                )
            )
            self._send(
                self._mav.command_ack_encode(
                    msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )
            self._after_ack(msg.command, params, result)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            if msg.target_system not in (0, self.cfg.system_id):
                return
            self._setpoint(msg)
        elif kind == "SET_GPS_GLOBAL_ORIGIN":
            if self.origin is None:
                self._set_origin(
                    LonLat(msg.longitude / 1e7, msg.latitude / 1e7, msg.altitude / 1000.0),
                    source="SET_GPS_GLOBAL_ORIGIN",
                )
                if not self.cfg.gps and self.origin is not None:
                    self.home = self.origin
                    self._send_home()
            else:
                self._event("SET_GPS_GLOBAL_ORIGIN ignored: origin already set")
        elif kind == "REQUEST_DATA_STREAM":
            # ArduPilot's legacy stream groups: 0 all, 2 extended status, 6 position.
            interval = 1.0 / msg.req_message_rate if msg.req_message_rate > 0 else 0.0
            if not msg.start_stop:
                interval = 0.0
            groups = {
                0: [
                    "LOCAL_POSITION_NED",
                    "GLOBAL_POSITION_INT",
                    "SYS_STATUS",
                    "EXTENDED_SYS_STATE",
                    "ATTITUDE",
                    "GPS_RAW_INT",
                ],
                2: ["SYS_STATUS", "EXTENDED_SYS_STATE", "GPS_RAW_INT"],
                6: ["LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"],
                10: ["ATTITUDE"],
            }
            for name in groups.get(msg.req_stream_id, []):
                self._intervals[name] = interval
        elif kind == "PARAM_REQUEST_LIST":
            for i, (pid, val) in enumerate(self._params().items()):
                self._send_param(pid, val, i)
        elif kind == "PARAM_REQUEST_READ":
            self._param_read(msg.param_id, msg.param_index)
        elif kind == "PARAM_SET":
            pid = msg.param_id
            self._param_overrides[pid] = float(msg.param_value)
            self._param_read(pid, -1)

    def _params(self) -> dict[str, float]:
        cfg = self.cfg
        if self.flavour == M.PX4:
            base = {
                "COM_OF_LOSS_T": cfg.offboard_loss_s,
                "COM_OBL_RC_ACT": 4.0 if cfg.offboard_loss_action == "land" else 5.0,
                "COM_DISARM_PRFLT": cfg.disarm_delay_s,
                "MIS_TAKEOFF_ALT": 2.5,
                "MPC_XY_VEL_MAX": cfg.max_speed_mps,
                "NAV_DLL_ACT": 0.0,
            }
        else:
            base = {
                "DISARM_DELAY": cfg.disarm_delay_s,
                "RTL_ALT": cfg.rtl_alt_m * 100,
                "FS_GCS_ENABLE": 0.0,
                "WPNAV_SPEED": cfg.max_speed_mps * 100,
                "GUID_TIMEOUT": 3.0,
            }
        base.update(self._param_overrides)
        return base

    def _send_param(self, pid: str, value: float, index: int) -> None:
        params = self._params()
        self._send(
            self._mav.param_value_encode(
                pid.encode()[:16], value, mavlink2.MAV_PARAM_TYPE_REAL32, len(params), index
            )
        )

    def _param_read(self, pid: str, index: int) -> None:
        params = self._params()
        names = list(params)
        if index >= 0 and index < len(names):
            pid = names[index]
        if pid in params:
            self._send_param(pid, params[pid], names.index(pid))

    def _setpoint(self, msg: Any) -> None:
        used = False
        mode = self.mode
        frame_ok = msg.coordinate_frame == M.MAV_FRAME_LOCAL_NED
        pos_given = (msg.type_mask & 0b111) == 0
        if self.flavour == M.PX4:
            # Any setpoint counts as proof of life for OFFBOARD.
            if self.t_s - self._last_sp_t > self.cfg.offboard_loss_s:
                self._sp_stream_start = self.t_s
            self._last_sp_t = self.t_s
            if mode == "offboard" and frame_ok and pos_given and self._position_valid():
                used = True
        else:
            # ArduCopter ignores position targets outside GUIDED, and on the ground
            # it needs MAV_CMD_NAV_TAKEOFF to leave it.
            if mode == "guided" and frame_ok and pos_given and not self.landed and self.armed:
                used = True
        if used:
            self.target = np.array([msg.x, msg.y, msg.z], dtype=float)
        self.setpoints.append(
            ReceivedSetpoint(
                self.t_s,
                msg.coordinate_frame,
                msg.type_mask,
                float(msg.x),
                float(msg.y),
                float(msg.z),
                math.degrees(msg.yaw),
                mode,
                used,
            )
        )

    def _offboard_stream_ok(self) -> bool:
        return (
            self.t_s - self._last_sp_t <= self.cfg.offboard_loss_s
            and self.t_s - self._sp_stream_start >= min(0.5, self.cfg.offboard_loss_s / 2)
        )

    def _command(self, command: int, p: tuple[float, ...]) -> int:
        if command == M.MAV_CMD_DO_SET_MODE:
            return self._cmd_set_mode(int(_num(p[1])), int(_num(p[2])))
        if command == M.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._cmd_arm(_num(p[0]) >= 0.5, _num(p[1]) == 21196)
        if command == M.MAV_CMD_NAV_TAKEOFF:
            return self._cmd_takeoff(p[6])
        if command == M.MAV_CMD_NAV_LAND:
            if not self.armed:
                return M.MAV_RESULT_DENIED
            self._set_mode("land", why="MAV_CMD_NAV_LAND")
            return M.MAV_RESULT_ACCEPTED
        if command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            if not self.armed:
                return M.MAV_RESULT_DENIED
            self._set_mode("rtl", why="MAV_CMD_NAV_RETURN_TO_LAUNCH")
            return M.MAV_RESULT_ACCEPTED
        if command == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            name = _MSG_NAME.get(int(_num(p[0])))
            if name is None:
                return M.MAV_RESULT_UNSUPPORTED
            if _num(p[1]) < 0:
                self._intervals[name] = 0.0
            elif _num(p[1]) == 0:
                self._intervals[name] = 1.0 / self.cfg.position_rate_hz
            else:
                self._intervals[name] = p[1] / 1e6
            self._next_due[name] = 0.0
            return M.MAV_RESULT_ACCEPTED
        if command in (
            M.MAV_CMD_REQUEST_MESSAGE,
            M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
            M.MAV_CMD_GET_HOME_POSITION,
        ):
            if command == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
                name = "AUTOPILOT_VERSION"
            elif command == M.MAV_CMD_GET_HOME_POSITION:
                name = "HOME_POSITION"
            else:
                name = _MSG_NAME.get(int(_num(p[0])), "")
            if name not in _MSG_NAME.values():
                return M.MAV_RESULT_UNSUPPORTED
            if name in ("HOME_POSITION", "GPS_GLOBAL_ORIGIN") and self.origin is None:
                return M.MAV_RESULT_TEMPORARILY_REJECTED
            self._pending_reply = name
            return M.MAV_RESULT_ACCEPTED
        return M.MAV_RESULT_UNSUPPORTED

    def _after_ack(self, command: int, params: tuple[float, ...], result: int) -> None:
        if self._pending_reply is not None:
            msg = self._build(self._pending_reply)
            self._pending_reply = None
            if msg is not None:
                self._send(msg)

    def _cmd_set_mode(self, custom: int, sub: int) -> int:
        if self.flavour == M.PX4:
            name = M.decode_mode(M.PX4, (custom << 16) | (sub << 24))
            if name.startswith("px4:"):
                return M.MAV_RESULT_DENIED
            if name == "offboard" and not self._offboard_stream_ok():
                self._statustext(4, "Switching to Offboard is currently not available")
                return M.MAV_RESULT_TEMPORARILY_REJECTED
            if (
                name in ("offboard", "hold", "rtl", "land")
                and self.booted
                and not self._position_valid()
            ):
                self._statustext(4, f"Switching to {name} requires position")
                return M.MAV_RESULT_DENIED
        else:
            name = M.decode_mode(M.ARDUPILOT, custom)
            if name.startswith("ardupilot:"):
                return M.MAV_RESULT_DENIED
            if name in ("guided", "loiter", "rtl") and self.booted and not self._position_valid():
                self._statustext(4, f"Mode change to {name.upper()} failed: requires position")
                return M.MAV_RESULT_FAILED
        if not self.booted and self._boot_mode is not None:
            # Accepted now, undone when initialisation finishes (seen on ArduCopter SITL).
            self.mode = name
            self._event(f"mode {name} (during boot)")
            return M.MAV_RESULT_ACCEPTED
        self._set_mode(name, why="DO_SET_MODE")
        return M.MAV_RESULT_ACCEPTED

    def _prearm_failure(self) -> str | None:
        if self._refuse_arming is not None:
            return self._refuse_arming
        if self.flavour == M.PX4 and self.cfg.preflight_fail:
            return self.cfg.preflight_fail
        if not self.booted:
            return "System not ready (booting)"
        if self.t_s < self.cfg.prearm_s:
            return "Gyros still settling" if self.flavour == M.ARDUPILOT else "ekf2 not ready"
        if not self._position_valid():
            return "Need Position Estimate"
        return None

    def _cmd_arm(self, arm: bool, force: bool) -> int:
        if not arm:
            if not self.landed and not force:
                return M.MAV_RESULT_DENIED
            self._disarm("command")
            return M.MAV_RESULT_ACCEPTED
        if self.armed:
            return M.MAV_RESULT_ACCEPTED
        reason = self._prearm_failure()
        if reason is not None and not force:
            prefix = "PreArm: " if self.flavour == M.ARDUPILOT else "Preflight Fail: "
            self._statustext(2, prefix + reason)
            self._event(f"arming refused: {reason}")
            return M.MAV_RESULT_FAILED
        if self.flavour == M.ARDUPILOT and self.mode not in (
            "guided",
            "stabilize",
            "loiter",
            "althold",
            "poshold",
        ):
            self._statustext(2, f"Arm: Mode not armable ({self.mode})")
            return M.MAV_RESULT_FAILED
        self.armed = True
        self._armed_at = self.t_s
        self._took_off = False
        self.target = self.target if (self.flavour == M.PX4 and self.mode == "offboard") else None
        self._event("armed")
        return M.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, alt_m: float) -> int:
        if self.flavour == M.PX4:
            alt = alt_m if math.isfinite(alt_m) and alt_m > 0 else self._params()["MIS_TAKEOFF_ALT"]
            if not self.armed or not self.landed:
                return M.MAV_RESULT_DENIED
            self.target = np.array([self.pos[0], self.pos[1], -alt])
            self._set_mode("takeoff", why="MAV_CMD_NAV_TAKEOFF")
            return M.MAV_RESULT_ACCEPTED
        # ArduCopter: p7 is the altitude above home; FAILED unless armed, landed, GUIDED.
        if not self.armed or not self.landed or self.mode != "guided":
            self._statustext(4, "Takeoff failed: not armed, not landed or not GUIDED")
            return M.MAV_RESULT_FAILED
        if not math.isfinite(alt_m) or alt_m <= 0:
            return M.MAV_RESULT_DENIED
        self.target = np.array([self.pos[0], self.pos[1], -alt_m])
        self._took_off = True
        self._event(f"takeoff to {alt_m:.1f} m")
        return M.MAV_RESULT_ACCEPTED


_MSG_NAME = {v: k for k, v in M.MSG_ID.items()}


def _num(value: float) -> float:
    """A command parameter with NaN ("unset") read as 0."""
    return 0.0 if value is None or math.isnan(value) else float(value)


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
