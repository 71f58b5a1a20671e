"""Fly a geonav policy on PX4 or ArduPilot over MAVLink (pymavlink or MAVSDK backends).

Import the submodules you need; nothing heavy is imported here:
``vehicle`` (the Vehicle protocol and connection strings), ``pymavlink_backend``,
``mavsdk_backend``, ``conversion``, ``frames`` (each autopilot's lon/lat <-> NED
formula), ``safety``, ``pump``, ``sequence``,
``flight`` (the loop and :func:`geonav.mavlink_bridge.flight.fly`), ``emulator``
(a MAVLink vehicle emulator for tests and dry runs) and ``cli``.
"""
