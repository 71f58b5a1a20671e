"""Greedy and sampled evaluation of a run's final policies from every start cell.

The experiment runner's periodic and final evaluations draw a seeded sample of starts
(``eval_starts`` in the config; 100 in ``configs/paper.toml``). This script evaluates each
unit's final checkpoint (``RUN/units/STAGE/seed-N/result.json``) on the unit's own scene
and task set from every valid start of every task, the way ``geonav eval --max-starts``
does, and prints per stage the greedy SR and SPL per seed with the median [min-max],
beside the task set's exact random-walk SR. Each unit's figures are kept in
``eval_all_starts.json`` in its folder, so a second call (or one after an interruption)
only evaluates what is missing.

Run: ``.venv/bin/python scripts/eval_all_starts.py runs/paper --stages meta_isar60,meta_savn60
--seeds 0,1,2,3,4 --jobs 2``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

OUT = "eval_all_starts.json"
ALL = 10**9
"""--max-starts for "every start": larger than any task set's start count."""


def evaluate_unit(unit: str) -> dict[str, Any]:
    """Evaluate one unit's final checkpoint from every start; writes and returns the row."""
    import torch

    from geonav.experiments.runner import read_result
    from geonav.policy.evaluation import evaluate_checkpoint

    torch.set_num_threads(1)
    folder = Path(unit)
    result = read_result(folder)  # its paths are relative to the run folder
    if result is None:
        raise SystemExit(f"{folder / 'result.json'} cannot be read")
    summary, _ = evaluate_checkpoint(result["checkpoint"], result["scene"], result["tasks"],
                                     max_starts=ALL, seed=0)
    g, s = summary["greedy"], summary["sampled"]
    out = {"checkpoint": summary["checkpoint"], "starts": summary["starts"],
           "greedy_sr": g["sr"], "greedy_spl": g["spl"],
           "sampled_sr": s["sr"], "sampled_spl": s["spl"],
           "ablated_sr": (summary.get("ablated") or {}).get("sr"),
           "random_walk_sr": summary["random_walk_sr"], "blind_sr": summary["blind_sr"]}
    tmp = folder / f".{OUT}.tmp"
    tmp.write_text(json.dumps(out, indent=1))
    os.replace(tmp, folder / OUT)
    return out


def _opt(v: float | None) -> str:
    """A chance figure, or n/a for rows kept before it was recorded."""
    return "n/a" if v is None else f"{v:.3f}"


def _fmt(values: list[float]) -> str:
    return (f"{statistics.median(values):.2f} [{min(values):.2f}-{max(values):.2f}]"
            if values else "n/a")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="run folder (the one holding units/)")
    ap.add_argument("--stages", required=True, help="comma-separated stage names")
    ap.add_argument("--seeds", default=None, help="comma-separated seeds (default: all)")
    ap.add_argument("--jobs", type=int, default=2, help="evaluations run at once")
    args = ap.parse_args(argv)

    units: dict[str, list[Path]] = {}
    for stage in args.stages.split(","):
        folder = args.run / "units" / stage
        found = sorted(folder.glob("seed-*"), key=lambda p: int(p.name[5:]))
        if args.seeds is not None:
            want = {int(s) for s in args.seeds.split(",")}
            found = [p for p in found if int(p.name[5:]) in want]
        found = [p for p in found if (p / "result.json").exists()]
        if not found:
            raise SystemExit(f"no finished units of stage {stage!r} under {folder}")
        if json.loads((found[0] / "result.json").read_text()).get("mode") == "curriculum":
            raise SystemExit(f"stage {stage!r} is a curriculum: its task set holds every "
                             "level's altitude, so evaluate its final policy on the last "
                             "level's task set with `geonav eval CKPT --scene S --tasks T "
                             "--max-starts N`")
        units[stage] = found
    todo = [str(p) for ps in units.values() for p in ps if not (p / OUT).exists()]
    if todo:
        print(f"evaluating {len(todo)} final policies from every start ...", file=sys.stderr)
        if args.jobs <= 1:
            for unit in todo:
                evaluate_unit(unit)
                print(f"  done: {unit}", file=sys.stderr)
        else:
            with ProcessPoolExecutor(max_workers=args.jobs) as pool:
                for unit, _ in zip(todo, pool.map(evaluate_unit, todo), strict=True):
                    print(f"  done: {unit}", file=sys.stderr)

    print("| stage | starts | greedy SR per seed | greedy SR | greedy SPL | sampled SR | "
          "view-ablated greedy SR | random walk / view-blind |")
    print("|---|---|---|---|---|---|---|---|")
    for stage, ps in units.items():
        rows = [json.loads((p / OUT).read_text()) for p in ps]
        per = " / ".join(f"{r['greedy_sr']:.2f}" for r in rows)
        starts = sorted({r["starts"] for r in rows})
        print(f"| {stage} | {', '.join(map(str, starts))} | {per} "
              f"(seeds {', '.join(p.name[5:] for p in ps)}) | "
              f"{_fmt([r['greedy_sr'] for r in rows])} | "
              f"{_fmt([r['greedy_spl'] for r in rows])} | "
              f"{_fmt([r['sampled_sr'] for r in rows])} | "
              f"{_fmt([r['ablated_sr'] for r in rows if r.get('ablated_sr') is not None])} | "
              f"{rows[0]['random_walk_sr']:.3f} / {_opt(rows[0].get('blind_sr'))} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
