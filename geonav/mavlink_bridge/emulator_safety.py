"""The emulated autopilot's own safety: battery, GPS-loss failsafe, and its fence.

:class:`SafetyMixin` drains the battery while armed and warns as each autopilot does
(low, then critical, then its battery failsafe if configured); after a GPS loss in the
air it lands as an EKF failsafe would; it takes fence items over the mission protocol
(MISSION_COUNT -> MISSION_REQUEST_INT -> MISSION_ITEM_INT ... -> MISSION_ACK;
MISSION_CLEAR_ALL) and, once the autopilot's fence parameters enable it (PX4
``GF_ACTION`` 1-5; ArduPilot ``FENCE_ENABLE`` 1 with ``FENCE_ACTION``), enforces it in
the air: a breach is a STATUSTEXT and the configured action. Every failsafe sets
:attr:`Emulator.failsafe`, so the HEARTBEAT shows CRITICAL. The texts are close to
the autopilots' own (PX4 ``battery_status``/``commander``, ArduPilot ``AP_BattMonitor``,
``AC_Fence``), not copies.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from geonav.geo import LonLat
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.emulator_config import EmulatorFields

#: PX4 GF_ACTION -> mode (1 is a warning only); ArduPilot FENCE_ACTION -> mode.
_PX4_FENCE_ACTION = {2: "hold", 3: "rtl", 5: "land"}
_AP_FENCE_ACTION = {1: "rtl", 2: "land", 3: "rtl", 4: "brake", 5: "rtl"}


class SafetyMixin(EmulatorFields):
    """Battery, GPS-loss failsafe and fence (mixed into :class:`Emulator`)."""

    def _safety_step(self, dt: float) -> None:
        """One emulated time step of the autopilot's own safety checks."""
        if self.armed and self.cfg.battery_drain_pct_per_s > 0:
            self.battery = max(0.0, self.battery - self.cfg.battery_drain_pct_per_s * dt)
        self._battery_check()
        if (self._gps_lost_at is not None and not self.landed and self.armed
                and self.failsafe != "gps"
                and self.t_s - self._gps_lost_at >= self.cfg.gps_failsafe_s):
            self._statustext(2, "EKF failsafe: position lost, landing")
            self._enter_failsafe("gps", "land")
        self._fence_check()

    # ---------------------------------------------------------------- battery
    def _battery_check(self) -> None:
        cfg = self.cfg
        if self._battery_warned < 1 and 0 < self.battery <= cfg.battery_low_pct:
            self._battery_warned = 1
            self._statustext(4, "Low battery level! Return advised" if self.flavour == M.PX4
                             else f"Battery 1 is low {self._battery_volts():.2f}V")
        if self._battery_warned < 2 and self.battery <= cfg.battery_critical_pct:
            self._battery_warned = 2
            self._statustext(2, "Critical battery level!" if self.flavour == M.PX4
                             else f"Battery 1 is critical {self._battery_volts():.2f}V")
            if cfg.battery_failsafe != "none" and self.armed and not self.landed:
                self._enter_failsafe("battery", cfg.battery_failsafe)

    def _battery_volts(self) -> float:
        """A 4S pack: 16.8 V full, 13.2 V empty."""
        return 13.2 + 3.6 * self.battery / 100.0

    def _enter_failsafe(self, name: str, mode: str) -> None:
        self.failsafe = name
        self._event(f"failsafe: {name}")
        self._set_mode(mode, why=f"failsafe: {name}")

    # ------------------------------------------------------ fence: mission protocol
    def _mission(self, kind: str, msg: Any) -> None:
        """MISSION_COUNT / MISSION_ITEM_INT / MISSION_CLEAR_ALL of the fence type."""
        reply_to = (msg.get_srcSystem(), msg.get_srcComponent())
        mission_type = getattr(msg, "mission_type", 0)
        if kind == "MISSION_CLEAR_ALL":
            if mission_type == M.MAV_MISSION_TYPE_FENCE:
                self.fence_items = []
                self.fence_breached = False
                self._event("fence cleared")
            self._mission_ack(reply_to, mission_type, M.MAV_MISSION_ACCEPTED)
        elif kind == "MISSION_COUNT":
            if mission_type != M.MAV_MISSION_TYPE_FENCE:
                self._mission_ack(reply_to, mission_type, 3)  # UNSUPPORTED
                return
            self._upload = {"count": int(msg.count), "items": [None] * int(msg.count)}
            if msg.count == 0:
                self._finish_upload(reply_to)
            else:
                self._request_item(reply_to, 0)
        elif kind in ("MISSION_ITEM_INT", "MISSION_ITEM") and self._upload is not None:
            seq = int(msg.seq)
            if 0 <= seq < self._upload["count"]:
                self._upload["items"][seq] = msg
            missing = [i for i, it in enumerate(self._upload["items"]) if it is None]
            if missing:
                self._request_item(reply_to, missing[0])
            else:
                self._finish_upload(reply_to)

    def _request_item(self, to: tuple[int, int], seq: int) -> None:
        self._send(self._mav.mission_request_int_encode(to[0], to[1], seq,
                                                        M.MAV_MISSION_TYPE_FENCE))

    def _mission_ack(self, to: tuple[int, int], mission_type: int, result: int) -> None:
        self._send(self._mav.mission_ack_encode(to[0], to[1], result, mission_type))

    def _finish_upload(self, to: tuple[int, int]) -> None:
        assert self._upload is not None
        items = self._upload["items"]
        self._upload = None
        ok = {M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, M.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION}
        if any(it.command not in ok for it in items):
            self._mission_ack(to, M.MAV_MISSION_TYPE_FENCE, 3)  # UNSUPPORTED
            return
        self.fence_items = [_fence_item(it) for it in items]
        self.fence_breached = False
        self._event(f"fence uploaded: {len(items)} items")
        self._mission_ack(to, M.MAV_MISSION_TYPE_FENCE, M.MAV_MISSION_ACCEPTED)

    # ------------------------------------------------------- fence: enforcement
    def fence_action(self) -> str | None:
        """The breach action the fence parameters set (None: the fence is off)."""
        params = self._params()
        if not self.fence_items:
            return None
        if self.flavour == M.PX4:
            action = int(params.get("GF_ACTION", 2))
            return "warn" if action == 1 else _PX4_FENCE_ACTION.get(action)
        if int(params.get("FENCE_ENABLE", 0)) != 1:
            return None
        return _AP_FENCE_ACTION.get(int(params.get("FENCE_ACTION", 1)), "warn")

    def outside_fence(self, north_m: float, east_m: float) -> bool:
        """Whether a point of the local frame is outside the uploaded fence."""
        if self.origin is None or not self.fence_items:
            return False
        polygon = [(it[1], it[2]) for it in self.fence_items if it[0] == "vertex"]
        if polygon and not _inside([self._ne(q) for q in polygon], (north_m, east_m)):
            return True
        for kind, lat, lon, radius in self.fence_items:
            if kind == "circle":
                n, e = self._ne((lat, lon))
                if math.hypot(north_m - n, east_m - e) > radius:
                    return True
        return False

    def _ne(self, latlon: tuple[float, float]) -> tuple[float, float]:
        assert self._frame is not None
        return self._frame.to_ne(LonLat(latlon[1], latlon[0]))

    def _fence_check(self) -> None:
        if self.fence_breached or not self.armed or self.landed:
            return
        action = self.fence_action()
        if action is None or not self.outside_fence(float(self.pos[0]), float(self.pos[1])):
            return
        self.fence_breached = True
        self._event(f"fence breached ({action})")
        if self.flavour == M.PX4:
            self._statustext(2, "Geofence breached" + ("" if action == "warn" else
                                                       f": failsafe {action}"))
        else:
            self._statustext(2, "Fence Breached")
        if action != "warn":
            self._enter_failsafe("fence", action)


def _fence_item(msg: Any) -> tuple[str, float, float, float]:
    """(kind, lat, lon, radius m) of a fence item (x/y are lat/lon * 1e7 in *_INT)."""
    scale = 1e7 if msg.get_type() == "MISSION_ITEM_INT" else 1.0
    kind = "circle" if msg.command == M.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION else "vertex"
    return kind, msg.x / scale, msg.y / scale, float(msg.param1)


def _inside(polygon: list[tuple[float, float]], p: tuple[float, float]) -> bool:
    """Even-odd rule: whether ``p`` lies inside ``polygon`` (same axes)."""
    pts = np.asarray(polygon)
    inside = False
    j = len(pts) - 1
    for i in range(len(pts)):
        (yi, xi), (yj, xj) = pts[i], pts[j]
        if (yi > p[0]) != (yj > p[0]):
            x_cross = xi + (p[0] - yi) * (xj - xi) / (yj - yi)
            if p[1] < x_cross:
                inside = not inside
        j = i
    return inside
