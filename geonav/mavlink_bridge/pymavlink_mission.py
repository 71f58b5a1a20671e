"""The MAVLink mission protocol for fence items, on the pymavlink backend.

Upload (mavlink.io "Mission Protocol", ``mission_type`` FENCE = 1): MISSION_COUNT, then
the autopilot asks for each item with MISSION_REQUEST_INT (or the older
MISSION_REQUEST) and geonav answers with MISSION_ITEM_INT; the autopilot ends with
MISSION_ACK, ACCEPTED or a reason. Clearing is MISSION_CLEAR_ALL answered by
MISSION_ACK. A request that does not come is asked for again by re-sending the count
(or the last item), until the timeout. Items: one MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
per vertex (param1 = the vertex count, x/y = lat/lon * 1e7) and, for a distance limit,
one MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION (param1 = radius).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Protocol

from geonav.errors import CommandRejected, FlightTimeout
from geonav.mavlink_bridge import modes as M
from geonav.mavlink_bridge.vehicle import FenceSpec


class MissionLink(Protocol):
    """What the mission client needs of the pymavlink backend: a way to send, and the
    mission replies its receiver thread keeps (time, kind, message) under its lock."""

    _lock: threading.Condition
    mission_rx: collections.deque[tuple[float, str, Any]]

    def _send_raw(self, name: str, fields: dict[str, Any]) -> None: ...

#: MAV_MISSION_RESULT names for refusals.
MISSION_RESULTS = {
    0: "ACCEPTED", 1: "ERROR", 2: "UNSUPPORTED_FRAME", 3: "UNSUPPORTED", 4: "NO_SPACE",
    5: "INVALID", 13: "INVALID_SEQUENCE", 14: "DENIED", 15: "OPERATION_CANCELLED",
}


def fence_items(fence: FenceSpec) -> list[dict[str, Any]]:
    """MISSION_ITEM_INT fields (without seq and targets) for ``fence``."""
    items = []
    for v in fence.polygon:
        items.append(_item(M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, float(len(fence.polygon)),
                           v.lat_deg, v.lon_deg))
    if fence.circle is not None:
        centre, radius_m = fence.circle
        items.append(_item(M.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, float(radius_m),
                           centre.lat_deg, centre.lon_deg))
    return items


def _item(command: int, param1: float, lat_deg: float, lon_deg: float) -> dict[str, Any]:
    return {
        "frame": M.MAV_FRAME_GLOBAL, "command": command, "current": 0, "autocontinue": 0,
        "param1": param1, "param2": 0.0, "param3": 0.0, "param4": 0.0,
        "x": int(round(lat_deg * 1e7)), "y": int(round(lon_deg * 1e7)), "z": 0.0,
        "mission_type": M.MAV_MISSION_TYPE_FENCE,
    }


def upload_fence_items(v: MissionLink, fence: FenceSpec, timeout_s: float) -> None:
    """Upload ``fence``'s items.

    Raises:
        FlightTimeout: the autopilot stopped answering.
        CommandRejected: it answered MISSION_ACK with a refusal.
    """
    items = fence_items(fence)
    deadline = time.monotonic() + timeout_s
    since = time.monotonic()
    count = {"count": len(items), "mission_type": M.MAV_MISSION_TYPE_FENCE}
    v._send_raw("MISSION_COUNT", count)
    last: tuple[str, dict[str, Any]] = ("MISSION_COUNT", count)
    while True:
        got = _next_reply(v, since, min(deadline, time.monotonic() + 1.0))
        if got is None:
            if time.monotonic() >= deadline:
                raise FlightTimeout(f"fence upload: the autopilot stopped answering after "
                                    f"{timeout_s:.0f} s ({last[0]} sent)")
            v._send_raw(*last)  # lost on the way: ask again
            continue
        t, kind, msg = got
        since = t
        if kind == "MISSION_ACK":
            _check_ack(msg, "fence upload")
            return
        if msg.mission_type != M.MAV_MISSION_TYPE_FENCE or not 0 <= msg.seq < len(items):
            continue
        last = ("MISSION_ITEM_INT", {"seq": msg.seq, **items[msg.seq]})
        v._send_raw(*last)


def clear_fence_items(v: MissionLink, timeout_s: float) -> None:
    """MISSION_CLEAR_ALL for the fence, retried until its MISSION_ACK.

    Raises:
        FlightTimeout, CommandRejected: as :func:`upload_fence_items`.
    """
    deadline = time.monotonic() + timeout_s
    since = time.monotonic()
    while True:
        v._send_raw("MISSION_CLEAR_ALL", {"mission_type": M.MAV_MISSION_TYPE_FENCE})
        got = _next_reply(v, since, min(deadline, time.monotonic() + 1.0))
        if got is not None and got[1] == "MISSION_ACK":
            _check_ack(got[2], "fence clear")
            return
        if time.monotonic() >= deadline:
            raise FlightTimeout(f"fence clear: no MISSION_ACK within {timeout_s:.0f} s")


def _next_reply(v: MissionLink, since: float,
                until: float) -> tuple[float, str, Any] | None:
    """The first mission reply received after ``since``, waiting until ``until``."""
    with v._lock:
        while True:
            for entry in v.mission_rx:
                if entry[0] > since:
                    return entry
            left = until - time.monotonic()
            if left <= 0:
                return None
            v._lock.wait(left)


def _check_ack(msg: Any, what: str) -> None:
    if msg.type != M.MAV_MISSION_ACCEPTED:
        raise CommandRejected(f"{what}: MISSION_ACK {MISSION_RESULTS.get(msg.type, msg.type)}")
