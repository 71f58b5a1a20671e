"""The Vehicle factory: a connection string and a backend name -> a backend's Vehicle.

It sits above :mod:`~geonav.mavlink_bridge.vehicle` (the protocol) and both backends,
so the protocol module never imports its implementations. Each backend is imported
only when it is chosen (MAVSDK's native library loads only for ``mavsdk``).
"""

from __future__ import annotations

from geonav.errors import FlightError
from geonav.mavlink_bridge.vehicle import Vehicle, parse_connection

BACKENDS = ("pymavlink", "mavsdk")


def open_vehicle(
    url: str,
    backend: str = "pymavlink",
    *,
    baud: int | None = None,
    system_id: int | None = None,
) -> Vehicle:
    """A Vehicle for ``url`` with the chosen backend (not yet connected).

    Args:
        url: connection string (see :func:`~geonav.mavlink_bridge.vehicle.parse_connection`).
        backend: ``"pymavlink"`` or ``"mavsdk"``.
        baud: serial baud rate if ``url`` has none.
        system_id: only talk to this autopilot system id (None: the first seen).
    """
    conn = parse_connection(url, baud)
    if backend == "pymavlink":
        from geonav.mavlink_bridge.pymavlink_backend import PymavlinkVehicle

        return PymavlinkVehicle(conn, system_id=system_id)
    if backend == "mavsdk":
        from geonav.mavlink_bridge.mavsdk_backend import MavsdkVehicle

        return MavsdkVehicle(conn, system_id=system_id)
    raise FlightError(f"backend {backend!r}: use one of {BACKENDS}")
