"""Memory per vector-env worker on a whole-scene task (Gymnasium AsyncVectorEnv, SB3 SubprocVecEnv).

Builds a synthetic scene package (default: residential, 1100 m at 0.5 m/px, as the quick
experiment) and a whole-scene curriculum task set (75/45/15 m on a 15 m lattice, every
altitude visited), then for 1..K workers steps a random policy and reads each process's
``/proc/<pid>/smaps_rollup``:

* USS = Private_Clean + Private_Dirty of a worker (what killing it would free),
* Pss_Anon of a worker (its private heap: never shared, never reclaimable),
* PSS slope = (total PSS of parent + workers at K) - (at 1), divided by K - 1: the memory
  one extra worker costs the machine, shared pages split fairly.

The workers receive the env as a ``functools.partial(GeoNavEnv, scene, tasks)`` (pickled
by the vector env: the scene travels as its package path). ``--in-memory`` sends an
in-memory copy of the scene instead (its arrays are pickled into every worker: the
old behaviour), for comparison. A worker with a trivial Gymnasium env (CartPole) gives the
interpreter's own share.

``--augment K`` (default 8; 0 skips it) then measures the batched engine's observation
tables with imagery randomisation (geonav.augment: K variants plus the clean one): for a
meta-training set (15 regions of 10 x 10 cells at 300 m, the use it is meant for) and the
whole-scene set, the feature table a frozen random encoder gives (what the learner keeps)
and the growth of this process's peak RSS while building it (the V copies of the pixels
are never held at once), against the same without augmentation.

Usage: .venv/bin/python bench/bench_env_memory.py [--scene DIR] [--workers 1,2,4]
       [--steps 400] [--in-memory] [--no-sb3] [--augment K] [--only-augment]
Prints figures; not a test.
"""

from __future__ import annotations

import argparse
import functools
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

from geonav.env import GeoNavEnv  # noqa: E402
from geonav.scene import Scene  # noqa: E402
from geonav.tasks import whole_scene_tasks  # noqa: E402

MB = 1024 * 1024


def smaps(pid: int) -> dict[str, int]:
    """Bytes of each field of /proc/<pid>/smaps_rollup."""
    out = {}
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]:
        key, value = line.split(":", 1)
        out[key] = int(value.split()[0]) * 1024
    return out


def uss(m: dict[str, int]) -> int:
    return m["Private_Clean"] + m["Private_Dirty"]


def drive(vec, steps: int, seed: int) -> None:
    """Random actions; every task (altitude) gets visited because tasks cycle."""
    vec.reset(seed=seed)
    rng = np.random.default_rng(seed)
    n_actions = int(vec.single_action_space.n)
    for _ in range(steps):
        vec.step(rng.integers(0, n_actions, vec.num_envs))


def gym_async(env_fn, n: int, context: str | None):
    vec = gym.vector.AsyncVectorEnv([env_fn] * n, context=context)
    return vec, [p.pid for p in vec.processes]


class _SB3:
    """SB3's VecEnv API is step(actions) -> 4-tuple and reset() without a seed."""

    def __init__(self, env_fn, n: int, start_method: str | None) -> None:
        from stable_baselines3.common.vec_env import SubprocVecEnv

        # SB3's default start method is forkserver
        self.vec = SubprocVecEnv([env_fn] * n, start_method=start_method)
        self.num_envs = n
        self.single_action_space = self.vec.action_space

    def reset(self, seed: int) -> None:
        self.vec.seed(seed)
        self.vec.reset()

    def step(self, actions) -> None:
        self.vec.step(actions)

    def close(self) -> None:
        self.vec.close()


def sb3_subproc(env_fn, n: int, context: str | None):
    vec = _SB3(env_fn, n, context)
    return vec, [p.pid for p in vec.vec.processes]


def measure(make, env_fn, counts: list[int], steps: int, context: str | None = None
            ) -> list[tuple[int, float, float, float]]:
    rows = []
    for n in counts:
        vec, pids = make(env_fn, n, context)
        try:
            drive(vec, steps, seed=n)
            per = [smaps(pid) for pid in pids]
            me = smaps(os.getpid())
            total_pss = me["Pss"] + sum(m["Pss"] for m in per)
            rows.append((n, np.mean([uss(m) for m in per]) / MB,
                         np.mean([m["Pss_Anon"] for m in per]) / MB, total_pss / MB))
        finally:
            vec.close()
    return rows


def report(label: str, rows: list[tuple[int, float, float, float]]) -> None:
    for n, u, anon, total in rows:
        print(f"  {label}: {n} worker(s): USS/worker {u:6.1f} MB, anon/worker {anon:6.1f} MB, "
              f"total PSS {total:7.1f} MB")
    if len(rows) > 1:
        (n0, *_, t0), (n1, *_, t1) = rows[0], rows[-1]
        print(f"  {label}: PSS per extra worker {(t1 - t0) / (n1 - n0):.1f} MB")


def peak_rss() -> int:
    """Bytes of this process's peak resident set (VmHWM)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return 0


def reset_peak() -> None:
    """Reset VmHWM to the current RSS (Linux: write 5 to clear_refs)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def augment_tables(scene: Scene, whole, k: int) -> None:
    """Feature-table size and peak-RSS growth with K imagery variants vs none."""
    import time

    from geonav.augment import AugmentConfig
    from geonav.policy.config import NetConfig
    from geonav.policy.encoders import build_frozen_encoder
    from geonav.tasks import sample_meta_tasks
    from geonav.vecenv import LatticeVecEnv

    frozen = build_frozen_encoder(NetConfig(encoder="random"))
    meta = sample_meta_tasks(scene, 15, size_m=150.0, alt_m=300.0, step_m=15.0, seed=0)
    print(f"observation tables with imagery randomisation (K = {k} variants + clean, "
          f"frozen random encoder, F = {frozen.out_dim}):")
    for label, tasks in (("meta-training set (15 x 10x10 at 300 m)", meta),
                         ("whole-scene set (75/45/15 m)", whole)):
        for aug in (None, AugmentConfig(variants=k)):
            env = GeoNavEnv(scene, tasks)
            venv = LatticeVecEnv(env, 1, augment=aug)
            reset_peak()
            before = peak_rss()
            t0 = time.perf_counter()
            feats = venv.feature_table(frozen)
            dt = time.perf_counter() - t0
            grow = peak_rss() - before
            print(f"  {label}, {'K = ' + str(k) if aug else 'no augmentation'}: "
                  f"{venv.n_views} views, features {feats.numel() * 4 / MB:7.1f} MB "
                  f"(images would be {venv.table_bytes() / MB:7.1f} MB), peak RSS growth "
                  f"{grow / MB:7.1f} MB, built in {dt:5.1f} s")
            del feats, venv, env


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", help="a scene package (default: synthesise residential 1100 m)")
    ap.add_argument("--workers", default="1,2,4")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--in-memory", action="store_true",
                    help="also send an in-memory copy of the scene (arrays pickled per worker)")
    ap.add_argument("--no-sb3", action="store_true")
    ap.add_argument("--augment", type=int, default=8, metavar="K",
                    help="imagery variants for the table figures (0: skip them)")
    ap.add_argument("--only-augment", action="store_true",
                    help="only the imagery-randomisation table figures")
    args = ap.parse_args()
    counts = [int(c) for c in args.workers.split(",")]
    tmp = tempfile.mkdtemp()
    if args.scene is None:
        from geonav.tiles.ingest import ingest_synthetic

        ingest_synthetic("residential", out=os.path.join(tmp, "A"), name="A", size_m=1100.0,
                         gsd_m=0.5)
        args.scene = os.path.join(tmp, "A")
    scene = Scene.open(args.scene)
    tasks = whole_scene_tasks(scene, (75.0, 45.0, 15.0), step_m=15.0)
    shape = tasks.tasks[0].lattice.shape
    print(f"scene {scene.name}: {scene.width}x{scene.height} px; whole-scene task set: "
          f"{len(tasks.tasks)} altitudes on a {shape[0]}x{shape[1]} lattice")
    if args.augment > 0:
        augment_tables(scene, tasks, args.augment)
    if args.only_augment:
        return
    env_fn = functools.partial(GeoNavEnv, scene, tasks, task_sampling="cycle")
    import pickle

    print(f"pickled env: {len(pickle.dumps(GeoNavEnv(scene, tasks))) / 1024:.1f} kB")
    base_fn = functools.partial(gym.make, "CartPole-v1")
    print("Gymnasium AsyncVectorEnv (fork):")
    report("CartPole (interpreter only)", measure(gym_async, base_fn, counts, args.steps))
    report("GeoNav, scene package", measure(gym_async, env_fn, counts, args.steps))
    print("Gymnasium AsyncVectorEnv (forkserver):")
    report("CartPole (interpreter only)", measure(gym_async, base_fn, counts, args.steps,
                                                  "forkserver"))
    report("GeoNav, scene package", measure(gym_async, env_fn, counts, args.steps,
                                            "forkserver"))
    if args.in_memory:
        copy = Scene.from_arrays("A", np.array(scene.rgb), scene.origin, scene.gsd_m,
                                 dsm=None if scene.dsm is None else np.array(scene.dsm))
        mem_fn = functools.partial(GeoNavEnv, copy, tasks.tasks, camera=tasks.camera,
                                   task_sampling="cycle")
        print(f"pickled env, in-memory scene: {len(pickle.dumps(mem_fn)) / MB:.1f} MB")
        report("GeoNav, in-memory scene", measure(gym_async, mem_fn, counts, args.steps,
                                                  "forkserver"))
    if not args.no_sb3:
        print("SB3 SubprocVecEnv (forkserver; each worker imports SB3 and so torch):")
        report("CartPole (interpreter + SB3)", measure(sb3_subproc, base_fn, counts,
                                                        args.steps))
        report("GeoNav, scene package", measure(sb3_subproc, env_fn, counts, args.steps))
        print("SB3 SubprocVecEnv(start_method='fork'; workers share the parent's imports):")
        report("GeoNav, scene package", measure(sb3_subproc, env_fn, counts, args.steps,
                                                "fork"))
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
