"""How Ray's worker niceness slows a unit on a busy machine, in one run.

Ray starts its worker processes at nice 15 (``RAY_worker_niceness``, default 15). On a
machine whose cores are busy with other work at nice 0 (another experiment, a test
worker), a unit running as a Ray task then gets little CPU. This bench keeps every core
busy with a spinning process, starts a local Ray cluster (2 CPUs) at the default
niceness and then at ``RAY_worker_niceness=0``, and times, inside one Ray task each
time, what a unit does first: importing torch, torch._dynamo (pulled in by
``torch.optim``) and matplotlib's pyplot. It prints the task's niceness and the seconds,
median of ``--repeats`` fresh clusters per setting, and the ratio.

    python bench/bench_ray_niceness.py [--repeats 3]

Needs ray (``pip install 'geonav[ray]'``).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import time


def _spin(stop: mp.Event) -> None:  # type: ignore[valid-type]
    while not stop.is_set():  # type: ignore[attr-defined]
        sum(range(10_000))


def _imports() -> dict[str, float]:
    t0 = time.perf_counter()
    import torch  # noqa: F401

    t1 = time.perf_counter()
    import torch._dynamo  # noqa: F401

    t2 = time.perf_counter()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401

    t3 = time.perf_counter()
    return {"nice": float(os.nice(0)), "torch": t1 - t0, "dynamo": t2 - t1, "pyplot": t3 - t2,
            "total": t3 - t0}


def _one(niceness: str | None) -> dict[str, float]:
    import ray

    if niceness is None:
        os.environ.pop("RAY_worker_niceness", None)
    else:
        os.environ["RAY_worker_niceness"] = niceness
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1",
             log_to_driver=False)
    try:
        return ray.get(ray.remote(num_cpus=1)(_imports).remote())
    finally:
        ray.shutdown()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    stop = mp.Event()
    spinners = [mp.Process(target=_spin, args=(stop,), daemon=True)
                for _ in range(os.cpu_count() or 1)]
    for p in spinners:
        p.start()
    try:
        rows = {}
        for label, nice in (("Ray default", None), ("RAY_worker_niceness=0", "0")):
            runs = [_one(nice) for _ in range(args.repeats)]
            rows[label] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    finally:
        stop.set()
        for p in spinners:
            p.join(timeout=5)
    print(f"{os.cpu_count()} cores kept busy at nice 0; seconds inside one Ray task, median "
          f"of {args.repeats} fresh clusters")
    print(f"{'setting':<24}{'nice':>6}{'torch':>9}{'dynamo':>9}{'pyplot':>9}{'total':>9}")
    for label, r in rows.items():
        print(f"{label:<24}{r['nice']:>6.0f}{r['torch']:>9.2f}{r['dynamo']:>9.2f}"
              f"{r['pyplot']:>9.2f}{r['total']:>9.2f}")
    a, b = rows["Ray default"]["total"], rows["RAY_worker_niceness=0"]["total"]
    print(f"ratio default / niceness 0: {a / b:.1f}x")


if __name__ == "__main__":
    main()
