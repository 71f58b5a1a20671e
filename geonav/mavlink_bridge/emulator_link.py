"""The emulator's MAVLink transport: UDP (server or ``udpout``) or TCP on loopback.

:class:`LinkMixin` opens the socket the emulator listens on, polls it without
blocking, parses what each peer sends (one MAVLink parser per peer) and sends every
message to every peer; a dropped link (fault injection) silences both directions.
"""

from __future__ import annotations

import logging
import select
import socket
import time
from typing import Any

from geonav.errors import FlightError
from geonav.mavlink_bridge._mav import mavlink2
from geonav.mavlink_bridge.emulator_config import EmulatorFields

log = logging.getLogger("geonav.mavlink_bridge.emulator")


class Peer:
    def __init__(self, addr: Any, sock: socket.socket | None = None) -> None:
        self.addr = addr
        self.sock = sock
        self.parser = mavlink2.MAVLink(None, srcSystem=0, srcComponent=0)
        self.parser.robust_parsing = True



class LinkMixin(EmulatorFields):
    """Sockets, peers, receiving and sending (mixed into :class:`Emulator`)."""

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
            self._peers[self._udpout_addr] = Peer(self._udpout_addr)
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
                self._peers[addr] = Peer(addr, conn)
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
            peer = self._peers[addr] = Peer(addr)
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

    def _statustext(self, severity: int, text: str) -> None:
        """Send a STATUSTEXT (PX4: only to a link that has a listener, see
        :attr:`EmulatorConfig.statustext_gate`); every text is kept in :attr:`texts`."""
        sent = self._text_listener()
        self.texts.append((self.t_s, severity, text, sent))
        if sent:
            self._send(self._mav.statustext_encode(severity, text.encode()[:50]))

    def _text_listener(self) -> bool:
        """Whether PX4 would send STATUSTEXT now: a GCS heartbeat (any system), or an
        onboard controller's from the vehicle's own system, within 2.5 s (real time)."""
        if self.flavour != "px4" or not self.cfg.statustext_gate:
            return True
        window = 2.5 * self.cfg.time_scale
        for (sysid, _, mav_type), t in self.peer_heartbeat_ids.items():
            if self.t_s - t <= window and (
                mav_type == 6 or (mav_type == 18 and sysid == self.cfg.system_id)
            ):
                return True
        return False
