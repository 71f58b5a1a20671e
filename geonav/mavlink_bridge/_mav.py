"""One place that imports pymavlink, forcing MAVLink 2 and the common dialect.

pymavlink picks its wire protocol from the ``MAVLINK20`` environment variable
at import time (``mavutil.set_dialect``); MAVSDK and both autopilots speak
MAVLink 2, so it is set here before the import.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

if getattr(mavutil, "current_dialect", None) != "common" or "v20" not in mavutil.mavlink.__name__:
    mavutil.set_dialect("common")

__all__ = ["mavlink2", "mavutil"]
