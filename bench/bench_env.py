"""Environment throughput: random-policy steps/s at 84 px on one core, slice vs warp path,
and the time to open a 1.2 km scene package.

Usage: .venv/bin/python bench/bench_env.py [--scene DIR] [--repeats 5]
Prints medians over repeats. Not a test; figures go into README.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from geonav.camera import Camera, SliceRenderer, WarpRenderer  # noqa: E402
from geonav.env import GeoNavEnv  # noqa: E402
from geonav.scene import Scene  # noqa: E402
from geonav.tasks import sample_meta_tasks, whole_scene_tasks  # noqa: E402


class WarpEnv(GeoNavEnv):
    """GeoNavEnv rendering every observation with the warp path (no cache)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.warp = WarpRenderer(self.scene, self.camera)

    def _view(self, task_index, cell):  # what GeoNavEnv's observations are read through
        tm = self.task_maps[task_index]
        p = tm.lattice.center(cell)
        return self.warp.render(p.x_m, p.y_m, tm.task.alt_m)


def steps_per_s(env, n_steps: int, seed: int) -> float:
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 4, n_steps)
    env.reset(seed=seed)
    t0 = time.perf_counter()
    for a in actions:
        _, _, te, tr, _ = env.step(int(a))
        if te or tr:
            env.reset()
    return n_steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", help="a scene package (default: synthesise residential 1.2 km)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    tmp = None
    if args.scene is None:
        from geonav.tiles.ingest import ingest_synthetic

        tmp = tempfile.mkdtemp()
        t0 = time.perf_counter()
        ingest_synthetic("residential", out=os.path.join(tmp, "A"), name="A")
        print(f"synthesise + ingest 1.2 km residential: {time.perf_counter() - t0:.1f} s")
        args.scene = os.path.join(tmp, "A")
    opens = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        scene = Scene.open(args.scene)
        opens.append(time.perf_counter() - t0)
    print(f"open scene {scene.width}x{scene.height} px: median {statistics.median(opens):.3f} s")
    cam = Camera(84, 90.0)
    meta = sample_meta_tasks(scene, 4, seed=0, camera=cam)
    whole = whole_scene_tasks(scene, (75.0, 45.0, 15.0), camera=cam)
    for label, ts in (("meta 300 m", meta), ("whole-scene 75/45/15 m", whole)):
        env = GeoNavEnv(scene, ts)
        steps_per_s(env, 20000, 0)  # warm the observation cache
        slice_rates = [steps_per_s(env, 50000, s) for s in range(args.repeats)]
        warp_rates = [steps_per_s(WarpEnv(scene, ts), 5000, s) for s in range(args.repeats)]
        print(f"{label}: slice path (cached) median {statistics.median(slice_rates):,.0f} "
              f"steps/s; warp path median {statistics.median(warp_rates):,.0f} steps/s")
    sl, wr = SliceRenderer(scene, cam), WarpRenderer(scene, cam)
    for alt in (300.0, 75.0, 45.0, 15.0):
        sl.render(0.0, 0.0, alt)
        rng = np.random.default_rng(0)
        pts = rng.uniform(-150, 150, (20000, 2))
        t0 = time.perf_counter()
        for x, y in pts:
            sl.render(x, y, alt)
        t1 = time.perf_counter()
        for x, y in pts[:4000]:
            wr.render(x, y, alt, 37.0)
        t2 = time.perf_counter()
        print(f"render {alt:>5.0f} m: slice {20000 / (t1 - t0):,.0f} obs/s, "
              f"warp (yaw 37 deg) {4000 / (t2 - t1):,.0f} obs/s")
    if tmp:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
