"""Evaluation cost: greedy + sampled from every start, per-episode reference vs lock-step.

    python bench/bench_eval.py [--repeats 3]

On the quick experiment's scene-B task (48 starts), with an untrained network (the worst
case: most greedy episodes run to the cap). Prints the median seconds of ``evaluate_both`` by both
paths and their ratio, measured side by side.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_learning import quick_b_task  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    args = ap.parse_args()
    import torch

    from geonav.policy import evaluation as ev
    from geonav.policy.config import NetConfig
    from geonav.policy.envs import EnvFactory
    from geonav.policy.model import ActorCritic

    torch.set_num_threads(1)
    scene, tasks = quick_b_task(Path(args.cache))
    env = EnvFactory(scene, tasks)()
    n_px = int(env.observation_space["image"].shape[0])
    torch.manual_seed(0)
    model = ActorCritic(NetConfig(obs_size_px=n_px))
    starts = ev.all_starts(env, 100)
    times: dict[str, list[float]] = {"reference": [], "lock-step": []}
    for _ in range(args.repeats):
        for name in times:
            t0 = time.perf_counter()
            for greedy in (True, False):
                if name == "reference":
                    ev.evaluate(model, env, starts=starts, greedy=greedy)
                else:
                    ev.evaluate_lockstep(model, env, starts, greedy=greedy)
            times[name].append(time.perf_counter() - t0)
    ref, fast = (statistics.median(times[k]) for k in ("reference", "lock-step"))
    print(f"{len(starts)} starts x (greedy + sampled), trainable CNN {n_px} px, untrained: "
          f"reference {ref:.2f} s, lock-step {fast:.2f} s, {ref / fast:.1f}x")


if __name__ == "__main__":
    main()
