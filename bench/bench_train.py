"""A3C training throughput (environment steps/s) next to the network-only figure.

For the small trainable CNN at 84 px and for frozen cached features (the random
frozen CNN; ResNet18 features would cost the same once cached), with 1 and 2
worker processes, this prints:

* train: steps/s of ``A3CTrainer`` in steady state (after a warm-up, start-up excluded);
* net:   steps/s of the network work alone (per step one batch-1 acting forward;
  per ``t_max`` steps the batched recompute, backward, clip and a fused Adam step)
  on random inputs, run in the same number of processes;
* ratio: median over the repeats of train / net (measured back to back).

Run: ``.venv/bin/python bench/bench_train.py [--seconds 8] [--repeats 3]``.
Figures are medians over the repeats. Targets on a 2-core machine: >= 300
steps/s (CNN, 2 workers), >= 500 (cached features, 2 workers), ratio >= 0.6.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time

import torch
import torch.multiprocessing as mp

from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.policy.a3c import A3CTrainer
from geonav.policy.callbacks import Callback
from geonav.policy.config import A3CConfig, NetConfig
from geonav.policy.losses import actor_critic_loss
from geonav.policy.model import ActorCritic
from geonav.policy.optim import SharedAdam
from geonav.testing import textured_scene, tiny_taskset


def env_factory(obs_px: int) -> functools.partial:
    scene = textured_scene(size_m=300.0)
    ts = tiny_taskset(scene, alt_m=75.0, cells=8, max_steps=70)
    return functools.partial(GeoNavEnv, scene, ts, camera=Camera(obs_px, 90.0))


class _Clock(Callback):
    def __init__(self, warmup: int) -> None:
        self.warmup = warmup
        self.n = 0
        self.t0 = 0.0
        self.steps = 0
        self.t1 = 0.0

    def on_episode(self, record):
        self.n += 1
        if self.n == self.warmup:
            self.t0 = time.perf_counter()
        elif self.n > self.warmup:
            self.steps += int(record["length"])
            self.t1 = time.perf_counter()

    @property
    def rate(self) -> float:
        return self.steps / max(self.t1 - self.t0, 1e-9)


class _StopAfter(Callback):
    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.start: float | None = None

    def on_episode(self, record):
        if self.start is None:
            self.start = time.perf_counter()
        return time.perf_counter() - self.start < self.seconds


def train_rate(net: NetConfig, workers: int, seconds: float) -> float:
    clock = _Clock(warmup=4 * max(workers, 1))
    cfg = A3CConfig(episodes=10**6, workers=workers, seed=0)
    trainer = A3CTrainer(env_factory(net.obs_size_px), net, cfg, callbacks=[clock,
                         _StopAfter(seconds)], keep_records=False)
    trainer.train()
    return clock.rate


def _net_loop(net: NetConfig, seconds: float, t_max: int, out: mp.Queue) -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = ActorCritic(net)
    opt = SharedAdam(model.parameters(), lr=1e-4, eps=1e-3, amsgrad=True, fused=True)
    if net.encoder == "cnn":
        views = torch.randint(0, 256, (t_max, 1, net.obs_size_px, net.obs_size_px, 3),
                              dtype=torch.uint8)
        target = torch.randint(0, 256, (1, net.obs_size_px, net.obs_size_px, 3),
                               dtype=torch.uint8)
    else:
        f = model.obs_embed.in_features
        views, target = torch.randn(t_max, 1, f), torch.randn(1, f)
    actions, rewards = [0] * t_max, [-0.01] * t_max
    params = list(model.parameters())
    steps, t0 = 0, None
    while True:
        if steps == 5 * t_max:
            t0, steps0 = time.perf_counter(), steps
        if t0 is not None and time.perf_counter() - t0 > seconds:
            break
        state = model.initial_state()
        with torch.inference_mode():  # as the trainer acts
            tf = model.features(target)
            s = state
            for t in range(t_max):
                _, _, s = model(views[t:t + 1], tf, s)
        for p in params:
            p.grad = None
        logits, values, _ = model(views, target, state)
        actor_critic_loss(logits[:, 0], values[:, 0], actions, rewards, 0.1).total.backward()
        torch.nn.utils.clip_grad_norm_(params, 100.0)
        opt.step()
        steps += t_max
    out.put((steps - steps0) / (time.perf_counter() - t0))


def net_rate(net: NetConfig, procs: int, seconds: float, t_max: int = 15) -> float:
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    ps = [ctx.Process(target=_net_loop, args=(net, seconds, t_max, q)) for _ in range(procs)]
    for p in ps:
        p.start()
    rates = [q.get() for _ in ps]
    for p in ps:
        p.join()
    return sum(rates)


def env_step_us(obs_px: int = 84, n: int = 20000) -> float:
    """Mean time of one ``env.step`` (observation cache warm), in microseconds."""
    env = env_factory(obs_px)()
    env.reset(seed=0)
    for a in range(4 * 64):  # warm the cache
        env.step(a % 4)
    env.reset(seed=0)
    t0 = time.perf_counter()
    for i in range(n):
        _, _, term, trunc, _ = env.step(i % 4)
        if term or trunc:
            env.reset()
    return (time.perf_counter() - t0) / n * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="measured seconds per run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    torch.set_num_threads(1)
    setups = {"cnn-84px (trainable)": NetConfig(encoder="cnn", obs_size_px=84),
              "cached features (frozen)": NetConfig(encoder="random", obs_size_px=84)}
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f}; {args.repeats} repeats of {args.seconds:g} s; "
          "medians (min-max)")
    print(f"{'setup':28s} {'W':>2s} {'train steps/s':>22s} {'net steps/s':>22s} {'ratio':>6s}")
    for name, net in setups.items():
        for w in args.workers:
            tr, nr = [], []
            for _ in range(args.repeats):  # interleaved, so both see the same machine load
                tr.append(train_rate(net, w, args.seconds))
                nr.append(net_rate(net, w, args.seconds))
            mt, mn = statistics.median(tr), statistics.median(nr)
            ratio = statistics.median(t / n for t, n in zip(tr, nr, strict=True))
            print(f"{name:28s} {w:2d} {mt:8.0f} ({min(tr):5.0f}-{max(tr):5.0f}) "
                  f"{mn:8.0f} ({min(nr):5.0f}-{max(nr):5.0f}) {ratio:6.2f}", flush=True)
    print(f"env.step from the observation cache: {env_step_us():.1f} us")
    print("load average (1, 5, 15 min) at the end: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))


if __name__ == "__main__":
    main()
