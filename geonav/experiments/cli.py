"""``geonav experiment run CONFIG.toml``: the transfer experiment runner."""

from __future__ import annotations

import argparse
from pathlib import Path

from geonav.cliutil import nonneg_int, positive_int


def _seeds(text: str) -> tuple[int, ...]:
    return tuple(nonneg_int(s.strip()) for s in text.split(","))


def add_parser(sub: argparse._SubParsersAction) -> None:
    exp = sub.add_parser("experiment", help="run transfer experiments from a TOML config")
    esub = exp.add_subparsers(dest="experiment_command", metavar="EXPERIMENT_COMMAND")
    exp.set_defaults(handler=lambda args: exp.print_help() or 0)
    p = esub.add_parser("run", help="run or resume an experiment; writes runs/NAME/")
    p.add_argument("config", help="experiment TOML (see configs/)")
    p.add_argument("--out", default="runs", help="parent folder of the run (default runs/)")
    p.add_argument("--only", action="append", help="run only this part (repeatable)")
    p.add_argument("--jobs", type=positive_int, default=2, help="units run in parallel (default 2)")
    p.add_argument("--seeds", type=_seeds, help="override the seeds, e.g. 0,1,2")
    p.add_argument("--name", help="override the experiment name (run folder)")
    p.add_argument("--fly", choices=["auto", "yes", "no"], default="auto",
                   help="fly the result in the MAVLink emulator when the config has [flight]")
    p.set_defaults(handler=run)
    p = esub.add_parser("report", help="re-write report.md and plots of a finished run")
    p.add_argument("config", help="experiment TOML")
    p.add_argument("--out", default="runs")
    p.add_argument("--only", action="append")
    p.set_defaults(handler=run_report)


def _overrides(args: argparse.Namespace) -> dict:
    o: dict = {}
    if getattr(args, "seeds", None):
        o["seeds"] = list(args.seeds)
    if getattr(args, "name", None):
        o["name"] = args.name
    return o


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from geonav.cliutil import progress_bar
    from geonav.experiments.config import load_config
    from geonav.experiments.runner import UnitEvent, run_experiment

    cfg = load_config(args.config, _overrides(args))
    bars: dict[str, tqdm] = {}
    overall = tqdm(total=0, desc=f"{cfg.name}: units", position=0, unit="unit", disable=None)

    def on_event(ev: UnitEvent) -> None:
        overall.total = ev.total_units
        overall.n = ev.done_units
        overall.refresh()
        if ev.unit is None:
            return
        key = ev.unit.key
        if ev.status in ("started", "progress"):
            bar = bars.get(key)
            if bar is None:
                bar = bars[key] = tqdm(total=ev.budget, desc=key, leave=False, unit="ep",
                                       position=len(bars) + 1, disable=None)
            bar.n = ev.episodes
            bar.refresh()
        elif ev.status in ("done", "failed"):
            bar = bars.pop(key, None)
            if bar is not None:
                bar.close()
            if ev.status == "failed":
                tqdm.write(f"unit {key} failed: {ev.message}")

    summary = run_experiment(cfg, args.out, only=args.only, jobs=args.jobs, on_event=on_event,
                             progress=progress_bar("inputs"))
    overall.close()
    root = Path(args.out) / cfg.name
    print(f"report: {root / 'report.md'}")
    for comp in summary.get("comparisons", []):
        parts = []
        for m, rec in comp["methods"].items():
            c = rec["convergence"]
            if c["median"] is not None:
                parts.append(f"{m} {c['median']:.0f}{'+' if c['median_censored'] else ''} ep")
        print(f"  {comp['name']}: " + ", ".join(parts))
    fly = args.fly == "yes" or (args.fly == "auto" and cfg.flight)
    if fly:
        from geonav.experiments.flight import fly_result

        record = fly_result(cfg, root)
        print(f"flight: {record}")
    return 1 if summary.get("failed") else 0


def run_report(args: argparse.Namespace) -> int:
    from geonav.experiments.config import load_config
    from geonav.experiments.report import write_report
    from geonav.experiments.runner import prepare_inputs

    cfg = load_config(args.config)
    root = Path(args.out) / cfg.name
    scenes, tasks = prepare_inputs(cfg, root)
    write_report(cfg, root, cfg.stages_for(args.only), scenes, tasks, {})
    print(f"report: {root / 'report.md'}")
    return 0
