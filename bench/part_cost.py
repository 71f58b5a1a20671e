"""What a part of an experiment cost: episodes, env steps and training wall time per unit.

Reads a run folder written by ``geonav experiment run`` (``RUN/units/STAGE/seed-N``,
every ``metrics.csv`` below it, curriculum levels included) and prints, per stage and
seed, the episodes and env steps trained and the training wall time (the last
``elapsed_s`` of each metrics file, summed over a curriculum's levels), with the steps per
second of wall time those imply. The last lines turn the part's env steps into a lower
bound on its wall time: the steps divided by ``--cores`` times a per-process rate in env
steps per CPU-second (``--rate``, e.g. the batched engine's figure from
``bench/bench_batched.py``). The bound assumes perfect load balance and no other load, so
a real run takes longer.

Run: ``.venv/bin/python bench/part_cost.py /work/runs/paper --stages curriculum,scratch15
--rate 3200``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path


def unit_cost(unit: Path, window: int = 500) -> tuple[int, int, float, float | None]:
    """(episodes, env steps, training wall seconds, training SR over the last ``window``
    episodes of its last metrics file) of one unit folder."""
    episodes = steps = 0
    wall = 0.0
    last_sr = None
    for m in sorted(unit.rglob("metrics.csv")):
        with m.open(newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            continue
        last = rows[-1]
        tail = rows[-window:]
        last_sr = sum(int(r["success"]) for r in tail) / len(tail)
        episodes += len(rows)
        steps += int(last["env_steps"])
        wall += float(last["elapsed_s"])
    return episodes, steps, wall, last_sr


def parse_rates(text: str | None, stages: list[str]) -> dict[str, float]:
    """``--rate``: one number for every stage, or ``STAGE=RATE`` pairs naming each."""
    if not text:
        return {}
    if "=" not in text:
        return dict.fromkeys(stages, float(text))
    rates = {}
    for pair in text.split(","):
        name, _, value = pair.partition("=")
        rates[name.strip()] = float(value)
    missing = [s for s in stages if s not in rates]
    if missing:
        raise SystemExit(f"--rate names no rate for {', '.join(missing)}")
    return rates


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="run folder (the one holding units/)")
    ap.add_argument("--stages", required=True, help="comma-separated stage names")
    ap.add_argument("--rate", default=None,
                    help="env steps per CPU-second of one process, for the bound: a number "
                         "or STAGE=RATE pairs separated by commas")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--window", type=int, default=500,
                    help="episodes of the final training SR column (the rule's W)")
    args = ap.parse_args()

    stages = args.stages.split(",")
    rates = parse_rates(args.rate, stages)
    total_steps, total_wall, bound = 0, 0.0, 0.0
    print("| stage | seed | episodes (metrics rows) | env steps | training wall s | steps/s | "
          f"training SR, last {args.window} |")
    print("|---|---|---|---|---|---|---|")
    for stage in stages:
        folder = args.run / "units" / stage
        if not folder.is_dir():
            raise SystemExit(f"no units for stage {stage!r} under {folder}")
        for unit in sorted(folder.glob("seed-*"), key=lambda p: int(p.name[5:])):
            ep, st, wall, sr = unit_cost(unit, args.window)
            total_steps += st
            total_wall += wall
            if rates:
                bound += st / (rates[stage] * args.cores)
            print(f"| {stage} | {unit.name[5:]} | {ep:,} | {st:,} | {wall:,.0f} | "
                  f"{st / max(wall, 1e-9):,.0f} | {'n/a' if sr is None else f'{sr:.3f}'} |")
    print(f"\ntotal: {total_steps:,} env steps, {total_wall:,.0f} s of training wall time "
          f"summed ({total_wall / 3600:.2f} h; {total_wall / 3600 / args.cores:.2f} h on "
          f"{args.cores} cores if perfectly balanced)")
    if rates:
        each = ", ".join(f"{k} {v:,.0f}" for k, v in rates.items())
        print(f"at {each} env steps per CPU-second per process on {args.cores} cores: at "
              f"least {bound:,.0f} s ({bound / 3600:.2f} h) of wall time")


if __name__ == "__main__":
    main()
