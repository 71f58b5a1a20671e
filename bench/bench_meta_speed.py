"""Batched meta-training throughput of this tree next to another revision's, side by side.

Runs ``bench_batched.run_batched`` (the bench problem and meta-training rows of
``bench_batched.py``: ISAR base second and first order, A3C base, SAVN base; B is the
meta-batch) in fresh subprocesses, alternating between this tree and ``--ref`` (a
checkout of an earlier revision, for example ``git archive REV | tar -x -C DIR``), so
that both see the same machine load. Prints, per row, the median steps per CPU-second
over the rounds of each tree and their ratio (this tree / ref).

Run: ``.venv/bin/python bench/bench_meta_speed.py --ref DIR [--rows meta-isar2,meta-a3c]
[--batch 16] [--rounds 3] [--seconds 4]``. Figures on a shared machine vary with its
load; the ratio of one run is what to compare.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
SNIPPET = """
import json, sys, torch
sys.path.insert(0, "bench")
import bench_batched as bb
torch.set_num_threads(1)
print(json.dumps(bb.run_batched(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]))))
"""


def measure(tree: Path, row: str, batch: int, seconds: float) -> float:
    """Steps per CPU-second of one batched run of ``row`` with the code of ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", SNIPPET, row, str(batch), str(seconds)],
                         cwd=tree, env=env, capture_output=True, text=True, check=True)
    rates = json.loads(out.stdout.strip().splitlines()[-1])
    return float("nan") if rates is None else float(rates[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ref", required=True, type=Path, help="checkout of the revision to "
                    "compare with (its bench/bench_batched.py is used)")
    ap.add_argument("--rows", default="meta-isar2,meta-isar1,meta-a3c")
    ap.add_argument("--batch", type=int, default=16, help="meta-batch B")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=4.0, help="measured seconds per run")
    args = ap.parse_args()
    rows = args.rows.split(",")
    got: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.rounds):
        for row in rows:
            for name, tree in (("ref", args.ref.resolve()), ("this", HERE)):
                got.setdefault((row, name), []).append(
                    measure(tree, row, args.batch, args.seconds))
    print(f"steps per CPU-second at B = {args.batch}, median of {args.rounds} alternating "
          f"rounds (ref: {args.ref})")
    print(f"{'row':12s} {'ref':>8s} {'this':>8s} {'ratio':>6s}   runs ref / this")
    for row in rows:
        ref, this = (statistics.median(got[(row, n)]) for n in ("ref", "this"))
        runs = " ".join(f"{x:.0f}" for x in got[(row, "ref")]) + " / " + \
            " ".join(f"{x:.0f}" for x in got[(row, "this")])
        print(f"{row:12s} {ref:8.0f} {this:8.0f} {this / ref:6.2f}   {runs}", flush=True)


if __name__ == "__main__":
    main()
