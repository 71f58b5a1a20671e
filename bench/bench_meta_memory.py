"""Resident memory of batched meta-training over many episodes: does it stay flat?

Runs one batched meta-training row of ``bench_batched.py`` (the bench problem: an 8 x 8
lattice at 75 m, T = 70, frozen random CNN features, the default network; B is the
meta-batch) for ``--episodes`` episodes, in this process, and samples the resident set
size (``/proc/self/statm``) after every episode. Prints the RSS at a few points of the
run, and the growth per 1,000 episodes over the second half of the run, where the
allocator has warmed up: a trainer that keeps nothing across windows shows a growth near
0; one that leaks a window's graph shows megabytes per 1,000 episodes that go on growing.

Run: ``.venv/bin/python bench/bench_meta_memory.py [--rows meta-isar2,meta-a3c]
[--episodes 2000] [--batch 16]``. Each row runs in a fresh subprocess.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

SNIPPET = """
import json, os, sys, torch
sys.path.insert(0, "bench")
import bench_batched as bb
from geonav.policy.batched.meta import BATCHED_META
from geonav.policy.callbacks import Callback
from geonav.policy.meta_config import MetaConfig
torch.set_num_threads(1)
PAGE = os.sysconf("SC_PAGE_SIZE")

def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 2**20

class Sampler(Callback):
    def __init__(self, n):
        self.n, self.samples = n, []
    def on_episode(self, record):
        self.samples.append(rss_mb())
        return len(self.samples) < self.n

row, batch, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
algo, net, cfg, ms = bb.configs(row)
s = Sampler(n)
BATCHED_META[algo[5:]](bb.env_factory(ms), net, cfg,
                       MetaConfig(episodes=10**7, batch_tasks=batch, checkpoint_every=0),
                       callbacks=[s], keep_records=False, tensorboard=False).train()
print(json.dumps(s.samples))
"""


def measure(row: str, batch: int, episodes: int) -> list[float]:
    """RSS in MiB after each of ``episodes`` episodes of one meta-training run."""
    env = {**os.environ, "PYTHONPATH": str(HERE.parent)}
    out = subprocess.run([sys.executable, "-c", SNIPPET, row, str(batch), str(episodes)],
                         cwd=HERE.parent, env=env, capture_output=True, text=True,
                         check=True)
    return list(json.loads(out.stdout.strip().splitlines()[-1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", default="meta-isar2,meta-isar1,meta-a3c")
    ap.add_argument("--episodes", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=16, help="meta-batch B")
    args = ap.parse_args()
    print(f"resident memory (MiB) of batched meta-training, B = {args.batch}")
    marks = [args.episodes // 10, args.episodes // 4, args.episodes // 2, args.episodes]
    print(f"{'row':12s} " + " ".join(f"{'@' + str(m):>8s}" for m in marks)
          + f" {'MiB per 1k episodes (2nd half)':>32s}")
    for row in args.rows.split(","):
        rss = measure(row, args.batch, args.episodes)
        half = len(rss) // 2
        slope = (rss[-1] - rss[half]) / max(len(rss) - half, 1) * 1000.0
        print(f"{row:12s} " + " ".join(f"{rss[min(m, len(rss)) - 1]:8.0f}" for m in marks)
              + f" {slope:32.1f}", flush=True)


if __name__ == "__main__":
    main()
