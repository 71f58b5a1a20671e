"""What the flight tests share: the tiny policy meta, the cells flown, fast timeouts."""

from __future__ import annotations

from geonav.mavlink_bridge.sequence import Timeouts

META = {"obs_size_px": 32, "alt_m": 10.0, "step_m": 5.0, "fov_deg": 90.0}
START, TARGET = (5, 5), (7, 6)
# Upper bounds only: a passing flight never waits them out. connect_s is the longest: in
# two full-suite runs of stop 43 (2 workers, both cores busy) a module's first emulator
# link waited more than the former 10 s for its first HEARTBEAT.
FAST = Timeouts(
    connect_s=30,
    ready_s=10,
    position_s=10,
    command_s=3.0,
    mode_s=8,
    arm_s=8,
    arm_retry_s=0.3,
    takeoff_s=15,
    landing_s=20,
)


def fast_emulator(scene, autopilot: str, **kw):
    """An emulator homed at START's cell centre (5 m lattice) of ``scene``, at 6x time with
    short boot, pre-arm and position delays; ``kw`` sets any other EmulatorConfig field."""
    from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig
    from geonav.tasks import Lattice

    home = scene.frame.to_lonlat(Lattice(scene.bounds_m, 5.0).center(START), 0.0)
    kw.setdefault("offboard_loss_s", 3.0)
    kw.setdefault("prearm_s", 3.0)
    return Emulator(EmulatorConfig(autopilot=autopilot, home=home, time_scale=6.0, boot_s=1.0,
                                   origin_s=0.6, local_position_s=1.2, **kw))


def hook_policy(actions: list[int], at: int, hook):
    """A scripted policy (META) that runs ``hook`` before its call number ``at``."""
    from geonav.mavlink_bridge.flight import ScriptedPolicy

    class Hook(ScriptedPolicy):
        def act(self, image, target) -> int:
            if self.calls == at:
                hook()
            return super().act(image, target)

    return Hook(actions, META)
