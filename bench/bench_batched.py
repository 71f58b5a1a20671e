"""Throughput of the batched engine next to today's (async) trainers, in one run.

The bench problem of ``bench_train.py`` / ``bench_meta.py``: an 8 x 8 lattice at 75 m,
T = 70, 84 px views, the default network; frozen random CNN features (F = 2,592) unless
the row says "cnn" (the trainable CNN). For every algorithm it prints steps per second of
wall time and per CPU-second of this process (one torch thread), steady state after a
warm-up:

* ``async``: today's trainer in its single-process mode (``workers = 0``: one worker,
  the per-episode reference), so its per CPU-second figure is that of one worker;
* ``batched B``: the batched engine with B slots (B = 1, 16, 64, 256);
* ``ratio``: batched per CPU-second / async per CPU-second.

The ``isar2-cnn`` and ``savn-cnn`` rows train the CNN, adapted per slot in the inner
steps (:class:`~geonav.policy.batched.core.SlotDeltas`). Rows the batched engine does not
implement yet (packed meta-training and curriculum rows)
print ``n/a``; ``packed 4x16`` is 4 independent runs of 16 slots each in one
process batch (:mod:`geonav.policy.batched.packed`, each run its own parameters, Adam and
per-run batch of 16), to read beside ``B=16`` (one such run) and ``B=64`` (one run of
the same process batch). In the meta-training rows (ISAR base
second and first order, A3C base, SAVN base; ``meta-isar2-cnn`` and ``meta-a3c-cnn``
with per-task copies of the trainable CNN; :mod:`geonav.policy.batched.meta`) B is the
meta-batch, every task the bench task, and ``async`` is
:class:`~geonav.policy.meta.MetaTrainer` in one process; the ISAR and A3C bases stop at
B = 64 (``META_MAX_BATCH``). Last, the memory of the observation tables of the whole-scene
15 m task of a 1.2 km scene (images and frozen features) with B = 256 slots, and the
process's peak RSS.

``bench_meta_speed.py`` puts the batched meta-training rows of this tree next to those of
another revision (alternating runs), for before/after ratios of an engine change.

Run: ``.venv/bin/python bench/bench_batched.py [--seconds 4] [--only a3c,isar2]``.
Figures on a shared machine vary with its load; compare the ratios of one run.
"""

from __future__ import annotations

import argparse
import functools
import resource
import time
from dataclasses import replace

import torch

from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.policy.callbacks import Callback
from geonav.policy.config import A3CConfig, NetConfig
from geonav.testing import textured_scene, tiny_taskset

BATCHES = (1, 16, 64, 256)
META_MAX_BATCH = 64
"""Meta-training with the ISAR and A3C bases keeps B copies of the network, their
gradients, task gradients and Adam moments (about 12 MB a slot for the bench network):
B = 256 would take 3 GB, so those rows stop at 64."""


def env_factory(max_steps: int = 70) -> functools.partial:
    scene = textured_scene(size_m=300.0)
    ts = tiny_taskset(scene, alt_m=75.0, cells=8, max_steps=max_steps)
    return functools.partial(GeoNavEnv, scene, ts, camera=Camera(84, 90.0))


class Clock(Callback):
    """Counts env steps of finished episodes after a warm-up; stops after ``seconds``."""

    def __init__(self, warmup: int, seconds: float) -> None:
        self.warmup, self.seconds = warmup, seconds
        self.n = self.steps = 0
        self.t0 = self.c0 = self.t1 = self.c1 = 0.0

    def on_episode(self, record):
        self.n += 1
        if self.n == self.warmup:
            self.t0, self.c0 = time.perf_counter(), time.process_time()
        elif self.n > self.warmup:
            self.steps += int(record["length"])
            self.t1, self.c1 = time.perf_counter(), time.process_time()
            return self.t1 - self.t0 < self.seconds
        return True

    def rates(self) -> tuple[float, float]:
        return (self.steps / max(self.t1 - self.t0, 1e-9),
                self.steps / max(self.c1 - self.c0, 1e-9))


def configs(kind: str):
    """(algo, NetConfig, config, max_steps) of a bench row."""
    from geonav.policy.meta_config import ISARConfig, SAVNConfig

    frozen = NetConfig(encoder="random", obs_size_px=84)
    # eval_every = 0: training throughput only (the periodic evaluation of every start is
    # the reference per-step evaluator for both engines, at the same episode interval)
    common = dict(episodes=10**7, workers=0, seed=0, checkpoint_every=0, eval_every=0)
    return {
        "a3c": ("a3c", frozen, A3CConfig(**common), 70),
        "a3c-cnn": ("a3c", replace(frozen, encoder="cnn"), A3CConfig(**common), 70),
        "ppo": ("ppo", frozen, None, 70),
        "isar2": ("isar", frozen, ISARConfig(**common, second_order=True), 70),
        "isar1": ("isar", frozen, ISARConfig(**common, second_order=False), 70),
        "savn": ("savn", frozen, SAVNConfig(**common), 70),
        "isar2-cnn": ("isar", replace(frozen, encoder="cnn"),
                      ISARConfig(**common, second_order=True), 70),
        "savn-cnn": ("savn", replace(frozen, encoder="cnn"), SAVNConfig(**common), 70),
        "curriculum-stage": ("isar", frozen, ISARConfig(**common), 120),
        "meta-isar2": ("meta-isar", frozen, ISARConfig(**common, second_order=True), 70),
        "meta-isar1": ("meta-isar", frozen, ISARConfig(**common, second_order=False), 70),
        "meta-a3c": ("meta-a3c", frozen, A3CConfig(**common), 70),
        "meta-savn": ("meta-savn", frozen, SAVNConfig(**common), 70),
        "meta-isar2-cnn": ("meta-isar", replace(frozen, encoder="cnn"),
                           ISARConfig(**common, second_order=True), 70),
        "meta-a3c-cnn": ("meta-a3c", replace(frozen, encoder="cnn"), A3CConfig(**common), 70),
    }[kind]


def run_async(kind: str, seconds: float) -> tuple[float, float]:
    from geonav.policy.engine import resolve
    from geonav.policy.meta import MetaTrainer
    from geonav.policy.meta_config import MetaConfig

    algo, net, cfg, ms = configs(kind)
    if algo == "ppo":
        return float("nan"), float("nan")
    clock = Clock(3, seconds)
    if algo.startswith("meta-"):
        t = MetaTrainer(env_factory(ms), net, algo[5:], cfg,
                        MetaConfig(episodes=10**7, workers=0, checkpoint_every=0),
                        callbacks=[clock], keep_records=False, tensorboard=False)
    else:
        t = resolve(algo, "async").cls(env_factory(ms), net, cfg, callbacks=[clock],
                                      keep_records=False, tensorboard=False)
    t.train()
    return clock.rates()


def run_batched(kind: str, batch: int, seconds: float) -> tuple[float, float] | None:
    from geonav.policy.batched.ppo import PPOConfig
    from geonav.policy.engine import resolve

    algo, net, cfg, ms = configs(kind)
    if algo.startswith("meta-"):
        from geonav.policy.batched.meta import BATCHED_META

        if algo != "meta-savn" and batch > META_MAX_BATCH:
            return None
        from geonav.policy.meta_config import MetaConfig

        clock = Clock(max(3, batch), seconds)
        BATCHED_META[algo[5:]](env_factory(ms), net, cfg,
                               MetaConfig(episodes=10**7, batch_tasks=batch, checkpoint_every=0),
                               callbacks=[clock], keep_records=False, tensorboard=False).train()
        return clock.rates()
    choice = resolve(algo, "batched", net, cfg)
    if choice.engine != "batched":
        return None
    if algo == "ppo":
        cfg = PPOConfig(episodes=10**7, seed=0, checkpoint_every=0, eval_every=0)
    clock = Clock(max(3, batch), seconds)
    t = choice.cls(env_factory(ms), net, cfg, batch=batch, callbacks=[clock],
                   keep_records=False, tensorboard=False)
    t.train()
    return clock.rates()


def run_packed(kind: str, runs: int, batch: int, seconds: float) -> tuple[float, float] | None:
    """Steps/s of ``runs`` packed runs of ``batch`` slots each (A3C, PPO, ISAR, SAVN)."""
    from geonav.policy.batched.packed import pack, packing_refusal
    from geonav.policy.batched.ppo import PPOConfig
    from geonav.policy.engine import resolve

    algo, net, cfg, ms = configs(kind)
    if algo not in ("a3c", "ppo", "isar", "savn"):
        return None
    if algo == "ppo":
        cfg = PPOConfig(episodes=10**7, seed=0, checkpoint_every=0, eval_every=0)
    choice = resolve(algo, "batched", net, cfg)
    members = [choice.cls(env_factory(ms), net, replace(cfg, seed=s), batch=batch,
                          keep_records=False, tensorboard=False) for s in range(runs)]
    if packing_refusal(members) is not None:
        return None
    driver = pack(members)
    driver._setup()
    for _ in range(3):
        driver.update()
    t0, c0, n0 = time.perf_counter(), time.process_time(), driver.venv.env_steps
    while time.perf_counter() - t0 < seconds:
        driver.update()
    steps = driver.venv.env_steps - n0
    return steps / (time.perf_counter() - t0), steps / (time.process_time() - c0)


def table_memory() -> None:
    from geonav.policy.encoders import build_frozen_encoder
    from geonav.tasks import whole_scene_tasks
    from geonav.vecenv import LatticeVecEnv

    scene = textured_scene(size_m=1200.0, gsd_m=0.5, seed=3)
    camera = Camera(84, 90.0)
    ts = whole_scene_tasks(scene, (75.0, 45.0, 15.0), camera=camera)
    task = [t for t in ts.tasks if t.alt_m == 15.0]
    env = GeoNavEnv(scene, task, camera=camera)
    t0 = time.perf_counter()
    venv = LatticeVecEnv(env, 256)
    images = venv.image_table()
    feats = venv.feature_table(build_frozen_encoder(NetConfig(encoder="random")))
    print(f"\nwhole-scene 15 m task ({venv.n_views} views) at B = 256: image table "
          f"{images.nbytes / 2**20:.0f} MiB, frozen features {feats.numel() * 4 / 2**20:.0f} "
          f"MiB (built in {time.perf_counter() - t0:.1f} s); peak RSS of this process "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=4.0, help="measured seconds per cell")
    ap.add_argument("--only", default=None, help="comma-separated rows (default: all)")
    ap.add_argument("--batches", default=",".join(map(str, BATCHES)))
    ap.add_argument("--no-memory", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    kinds = args.only.split(",") if args.only else ["a3c", "a3c-cnn", "ppo", "isar2", "isar1",
                                                      "savn", "isar2-cnn", "savn-cnn",
                                                      "meta-isar2", "meta-isar1",
                                                      "meta-a3c", "meta-savn",
                                                      "meta-isar2-cnn", "meta-a3c-cnn",
                                                      "curriculum-stage"]
    batches = [int(b) for b in args.batches.split(",")]
    head = f"{'row':17s} {'async wall':>10s} {'/cpu-s':>8s}"
    for b in batches:
        head += f" | {'B=' + str(b) + ' wall':>11s} {'/cpu-s':>8s} {'ratio':>6s}"
    print(head + " | packed 4x16")
    for kind in kinds:
        aw, ac = run_async(kind, args.seconds)
        line = f"{kind:17s} {aw:10.0f} {ac:8.0f}"
        for b in batches:
            r = run_batched(kind, b, args.seconds)
            if r is None:
                line += f" | {'n/a':>11s} {'':8s} {'':6s}"
            else:
                ratio = r[1] / ac if ac == ac and ac > 0 else float("nan")
                line += f" | {r[0]:11.0f} {r[1]:8.0f} {ratio:6.1f}"
        r = run_packed(kind, 4, 16, args.seconds)
        if r is None:
            line += " | n/a"
        else:
            ratio = r[1] / ac if ac == ac and ac > 0 else float("nan")
            line += f" | {r[0]:.0f} wall, {r[1]:.0f} /cpu-s, ratio {ratio:.1f}"
        print(line, flush=True)
    if not args.no_memory:
        table_memory()


if __name__ == "__main__":
    main()
