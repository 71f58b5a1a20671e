"""Control-loop latency frame -> setpoint (p50/p99) with the synthetic camera and an 84 px policy.

Runs the real per-step path of ``geonav.mavlink_bridge.flight`` on one core:
read the vehicle state, render the synthetic frame at the reported position
(WarpRenderer), run the policy, compute the next lattice target through
lon/lat into NED at an EKF origin that differs from the scene origin, check
it against the geofence and hand it to the setpoint pump (which sends a
real SET_POSITION_TARGET_LOCAL_NED over UDP to the emulator). Arrival
waiting is excluded: it is flight time, not loop latency.

The policy is ``geonav.policy.inference.PolicyRunner`` if a checkpoint is
given and that module exists; otherwise a tiny actor-critic-shaped torch net
(conv encoder on image+target, LSTM cell, 4-way policy head and value head),
and the printout says so.

    .venv/bin/python bench/bench_flight.py [--steps 500] [--checkpoint CKPT]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch import nn  # noqa: E402

from geonav.camera import Camera, WarpRenderer  # noqa: E402
from geonav.geo import LonLat, ScenePoint  # noqa: E402
from geonav.mavlink_bridge.camera_source import SyntheticFrames  # noqa: E402
from geonav.mavlink_bridge.conversion import TargetPlanner  # noqa: E402
from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig  # noqa: E402
from geonav.mavlink_bridge.pump import SetpointPump  # noqa: E402
from geonav.mavlink_bridge.safety import Geofence  # noqa: E402
from geonav.mavlink_bridge.vehicle import open_vehicle  # noqa: E402
from geonav.testing import textured_scene  # noqa: E402


class TinyActorCritic(nn.Module):
    """Stand-in policy: 84x84 image + target -> conv encoder -> LSTMCell(256) -> pi(4), v."""

    def __init__(self) -> None:
        super().__init__()
        self.enc = nn.Sequential(
            nn.Conv2d(6, 32, 8, 4),
            nn.ReLU(),
            nn.Conv2d(32, 64, 4, 2),
            nn.ReLU(),
            nn.Conv2d(64, 64, 3, 1),
            nn.ReLU(),
            nn.Flatten(),
            nn.Linear(64 * 7 * 7, 256),
            nn.ReLU(),
        )
        self.lstm = nn.LSTMCell(256, 256)
        self.pi = nn.Linear(256, 4)
        self.v = nn.Linear(256, 1)
        self.hx = None

    def reset(self) -> None:
        self.hx = None

    @torch.inference_mode()
    def act(self, image: np.ndarray, target: np.ndarray) -> int:
        x = (
            torch.from_numpy(np.concatenate([image, target], axis=2)).permute(2, 0, 1)[None].float()
            / 255
        )
        h, c = self.lstm(self.enc(x), self.hx)
        self.hx = (h, c)
        return int(torch.argmax(self.pi(h), dim=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--checkpoint", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        pinned = "pinned to one core"
    except (AttributeError, OSError):
        pinned = "not pinned"

    policy_name = "tiny actor-critic-shaped torch net (real geonav policy not used)"
    policy = None
    if args.checkpoint:
        try:
            from geonav.mavlink_bridge.flight import load_policy

            policy = load_policy(args.checkpoint)
            policy_name = f"geonav PolicyRunner from {args.checkpoint}"
        except Exception as err:  # report and fall back
            print(f"could not load the real policy ({err}); using the stand-in net")
    if policy is None:
        policy = TinyActorCritic().eval()
    scene = textured_scene(400.0, 0.5, towers=False)
    camera = Camera(84, 90.0)
    renderer = WarpRenderer(scene, camera)
    ekf_origin = scene.frame.to_lonlat(ScenePoint(37.0, -21.0), 0.0)
    t_start = time.monotonic()
    emu = Emulator(
        EmulatorConfig(
            autopilot="px4",
            home=ekf_origin,
            boot_s=0.0,
            origin_s=0.0,
            local_position_s=0.0,
            prearm_s=0.0,
        )
    ).start()
    vehicle = open_vehicle(emu.connect_url, "pymavlink")
    vehicle.connect(10.0)
    vehicle.request_telemetry(10.0, 3.0)
    t0 = time.monotonic()
    while (
        vehicle.state().position is None or vehicle.state().origin is None
    ) and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    s = vehicle.state()
    planner = TargetPlanner(
        scene.frame,
        s.origin or LonLat(ekf_origin.lon_deg, ekf_origin.lat_deg),
        s.position.down_m if s.position else 0.0,
        45.0,
        autopilot=vehicle.autopilot,
    )
    fence = Geofence.from_bounds(scene.bounds_m, 10.0)
    pump = SetpointPump(
        vehicle,
        rate_hz=15.0,
        deadline_s=5.0,
        fence_check=lambda ned: fence.check(planner.to_scene(ned)[0]),
    )
    # Render at the scene point 45 m above, as the reported position would be in flight.
    frames = SyntheticFrames(renderer, lambda ned: (planner.to_scene(ned)[0], 45.0))
    target_img = renderer.render(30.0, 30.0, 45.0)
    previous = ScenePoint(0.0, 0.0)
    pump.set_target(planner.to_ned(previous), 0.0)
    pump.start()
    policy.reset()
    lat_ms = []
    for i in range(args.steps + 20):
        t = time.perf_counter()
        state = vehicle.state()
        image = frames.frame(state)
        action = policy.act(image, target_img)
        nxt = planner.next_target(previous, action, 15.0)
        if not fence.contains(nxt):
            nxt = previous
        pump.set_target(planner.to_ned(nxt), 0.0)
        dt = (time.perf_counter() - t) * 1000
        previous = nxt if abs(nxt.x_m) < 100 and abs(nxt.y_m) < 100 else ScenePoint(0.0, 0.0)
        if i >= 20:
            lat_ms.append(dt)
    pump.stop()
    vehicle.close()
    wall_s = time.monotonic() - t_start
    emulated_s = emu.t_s
    gaps = np.asarray([g for g, _ in emu.steps_log])
    dts = np.asarray([d for _, d in emu.steps_log])
    emu.stop()
    a = np.asarray(lat_ms)
    print(f"policy: {policy_name}; torch threads {torch.get_num_threads()}; {pinned}")
    print(
        f"frame -> setpoint latency over {len(a)} steps (84 px synthetic camera, pymavlink, UDP):"
    )
    print(
        f"  p50 {np.percentile(a, 50):.2f} ms   p99 {np.percentile(a, 99):.2f} ms   "
        f"max {a.max():.2f} ms   "
        f"(target p99 < 20 ms: {'met' if np.percentile(a, 99) < 20 else 'NOT met'})"
    )
    print(
        f"emulator clock (time_scale 1): {emulated_s:.1f} emulated s in {wall_s:.1f} wall s "
        f"(one thread: ratio {emulated_s / wall_s:.3f}); loop gap p99 "
        f"{np.percentile(gaps, 99) * 1000:.1f} ms, max {gaps.max() * 1000:.1f} ms; "
        f"largest emulated step {dts.max():.3f} s (bound "
        f"{max(emu.cfg.max_dt_s, 0.02 * emu.cfg.time_scale):.2f} s)"
    )


if __name__ == "__main__":
    main()
