"""Fly a geonav policy on PX4 or ArduPilot over MAVLink (pymavlink or MAVSDK backends).

Import the submodules you need; nothing heavy is imported here. Arrows point down:

* ``flight`` (:func:`geonav.mavlink_bridge.flight.fly`, ``run_flight``: the driver and
  the only module that touches ``geonav.policy``) over the phases ``preflight``,
  ``autonomy`` (take-off, positioning, the step loop) and ``ending`` (end action,
  record), which share a ``context.FlightContext``; ``plan`` (settings and the plan
  checked before connecting), ``outcome`` (outcome words, exit codes, the result),
  ``signals``;
* ``sequence`` (gated phases on a vehicle: ready, position, mode, arm, take-off, land),
  ``pump`` (the setpoint stream), ``safety`` (fence, watchdogs), ``conversion`` and
  ``frames`` (scene -> lon/lat -> each autopilot's NED), ``camera_source``, ``record``;
* ``backends`` (``open_vehicle``: the factory) over ``pymavlink_backend`` (with
  ``pymavlink_mission``, the fence's mission protocol) and ``mavsdk_backend``, which
  share ``backend_common`` (telemetry store, checked commands, parameters, the fence's
  parameters), over ``vehicle`` (the ``Vehicle`` protocol, ``VehicleState``,
  ``FenceSpec``, connection strings), ``modes`` and ``folding``;
* ``emulator`` (a MAVLink vehicle emulator for tests and dry runs) over its parts
  ``emulator_config``, ``emulator_link``, ``emulator_physics``, ``emulator_messages``,
  ``emulator_safety`` (battery, failsafes, fence) and ``emulator_handlers``;
* ``cli`` (``geonav fly``, ``geonav emulator``).
"""
