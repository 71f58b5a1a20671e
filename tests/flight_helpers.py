"""What the flight tests share: the tiny policy meta, the cells flown, fast timeouts."""

from __future__ import annotations

from geonav.mavlink_bridge.sequence import Timeouts

META = {"obs_size_px": 32, "alt_m": 10.0, "step_m": 5.0, "fov_deg": 90.0}
START, TARGET = (5, 5), (7, 6)
# Upper bounds only: a passing flight never waits them out.
FAST = Timeouts(
    connect_s=10,
    ready_s=10,
    position_s=10,
    command_s=3.0,
    mode_s=8,
    arm_s=8,
    arm_retry_s=0.3,
    takeoff_s=15,
    landing_s=20,
)
