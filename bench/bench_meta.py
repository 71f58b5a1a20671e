"""Wall time per 70-step episode and steps/s with 2 workers: A3C, SAVN, ISAR (2nd/1st order).

Episodes are capped at 70 steps (T_max) on an 8x8 lattice at 75 m (some end earlier
on success, so the cost is measured per step), with frozen cached features (encoder
'random', 84 px, the default network sizes 256/256). Per algorithm: W worker processes
train for ``--seconds`` after a
warm-up; steps/s = environment steps / wall time; "s/ep70" = 70 / per-worker steps/s.

Run: ``.venv/bin/python bench/bench_meta.py [--seconds 10] [--repeats 3] [--workers 2]``.
Targets (2 cores): ISAR 2nd order >= 250 steps/s and <= 2.5x the A3C episode cost;
SAVN >= 200 steps/s. Medians over the repeats are printed.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time

from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.policy.a3c import A3CTrainer
from geonav.policy.callbacks import Callback
from geonav.policy.config import A3CConfig, NetConfig
from geonav.policy.isar import ISARTrainer
from geonav.policy.meta_config import ISARConfig, SAVNConfig
from geonav.policy.savn import SAVNTrainer
from geonav.testing import textured_scene, tiny_taskset


def env_factory(obs_px: int) -> functools.partial:
    scene = textured_scene(size_m=300.0)
    ts = tiny_taskset(scene, alt_m=75.0, cells=8, max_steps=70)
    return functools.partial(GeoNavEnv, scene, ts, camera=Camera(obs_px, 90.0))


class _Clock(Callback):
    def __init__(self, warmup: int, seconds: float) -> None:
        self.warmup, self.seconds = warmup, seconds
        self.n = self.steps = 0
        self.t0 = self.t1 = 0.0

    def on_episode(self, record):
        self.n += 1
        now = time.perf_counter()
        if self.n == self.warmup:
            self.t0 = now
        elif self.n > self.warmup:
            self.steps += int(record["length"])
            self.t1 = now
            return now - self.t0 < self.seconds
        return True

    @property
    def rate(self) -> float:
        return self.steps / max(self.t1 - self.t0, 1e-9)


def rate(kind: str, net: NetConfig, workers: int, seconds: float) -> float:
    clock = _Clock(2 * workers, seconds)
    common = dict(episodes=10**6, workers=workers, seed=0, checkpoint_every=0)
    if kind == "a3c":
        t = A3CTrainer(env_factory(net.obs_size_px), net, A3CConfig(**common),
                       callbacks=[clock], keep_records=False)
    elif kind == "savn":
        t = SAVNTrainer(env_factory(net.obs_size_px), net, SAVNConfig(**common),
                        callbacks=[clock], keep_records=False)
    else:
        t = ISARTrainer(env_factory(net.obs_size_px), net,
                        ISARConfig(second_order=kind == "isar-2nd", **common),
                        callbacks=[clock], keep_records=False)
    t.train()
    return clock.rate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--encoder", default="random", choices=["random", "cnn"])
    args = ap.parse_args()
    net = NetConfig(encoder=args.encoder, obs_size_px=84)
    rows = {}
    for kind in ("a3c", "savn", "isar-2nd", "isar-1st"):
        rs = [rate(kind, net, args.workers, args.seconds) for _ in range(args.repeats)]
        rows[kind] = statistics.median(rs)
        per_worker = rows[kind] / args.workers
        print(f"{kind:9s} steps/s (W={args.workers}) median {rows[kind]:7.1f}  "
              f"[{', '.join(f'{r:.0f}' for r in rs)}]   s/ep70 per worker "
              f"{70 / per_worker:.3f}", flush=True)
    a = rows["a3c"]
    print(f"episode cost vs A3C: savn {a / rows['savn']:.2f}x, isar-2nd "
          f"{a / rows['isar-2nd']:.2f}x, isar-1st {a / rows['isar-1st']:.2f}x")


if __name__ == "__main__":
    main()
