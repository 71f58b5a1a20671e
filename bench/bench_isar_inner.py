"""How far ISAR's inner step moves theta: |alpha * g| / |theta| per inner update.

    python bench/bench_isar_inner.py --alphas 1e-4,1e-3,1e-2 --episodes 200

Trains ISAR (the async reference, one process) on the quick experiment's scene-B task and
records, for every inner SGD step, the norm of the step over the norm of theta (all
parameters together), then prints the median and 90th percentile per alpha with the
greedy SR over all starts at the end. At a ratio near 1e-5 the inner loop is inert and ISAR
is A3C with windowed updates (ALGORITHMS.md (c); the paper's claim 1 depends on it).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_learning import quick_b_env  # noqa: E402

import geonav.policy.isar as isar_mod  # noqa: E402
from geonav.policy.config import NetConfig  # noqa: E402
from geonav.policy.evaluation import evaluate_both  # noqa: E402
from geonav.policy.isar import ISARTrainer  # noqa: E402
from geonav.policy.meta_config import ISARConfig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--alphas", default="1e-4,1e-3,1e-2")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    factory, env, n_px = quick_b_env(Path(args.cache))
    ratios: list[float] = []
    original = isar_mod.sgd_step

    def recording(params, loss, lr, *, create_graph, names=None):  # type: ignore[no-untyped-def]
        out = original(params, loss, lr, create_graph=create_graph, names=names)
        with torch.no_grad():
            step = sum(float((out[k] - params[k]).pow(2).sum()) for k in params)
            norm = sum(float(params[k].pow(2).sum()) for k in params)
        ratios.append((step / max(norm, 1e-30)) ** 0.5)
        return out

    isar_mod.sgd_step = recording
    print("| alpha | inner steps | median |alpha g| / |theta| | 90th pct | greedy SR at end |")
    print("|---|---|---|---|---|")
    for alpha in (float(a) for a in args.alphas.split(",")):
        ratios.clear()
        cfg = ISARConfig(episodes=args.episodes, workers=0, lr=5e-4, alpha=alpha,
                         seed=args.seed, eval_every=0)
        t = ISARTrainer(factory, NetConfig(obs_size_px=n_px), cfg, keep_records=False)
        t.train()
        sr = evaluate_both(t.model, env, max_starts=None)["row"]["greedy_sr"]
        r = np.array(ratios)
        print(f"| {alpha:g} | {len(r)} | {np.median(r):.2e} | {np.quantile(r, 0.9):.2e} | "
              f"{sr:.2f} |", flush=True)
    isar_mod.sgd_step = original


if __name__ == "__main__":
    main()
