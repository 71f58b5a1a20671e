"""``geonav experiment run CONFIG.toml``: the transfer experiment runner."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from geonav.cliutil import add_command_group, nonneg_int, positive_int


def _seeds(text: str) -> tuple[int, ...]:
    return tuple(nonneg_int(s.strip()) for s in text.split(","))


def add_parser(sub: argparse._SubParsersAction) -> None:
    esub = add_command_group(sub, "experiment", help="run transfer experiments from a TOML config",
                             metavar="EXPERIMENT_COMMAND")
    p = esub.add_parser("run", help="run or resume an experiment; writes runs/NAME/")
    p.add_argument("config", help="experiment TOML (see configs/)")
    p.add_argument("--out", default="runs", help="parent folder of the run (default runs/)")
    p.add_argument("--only", action="append", help="run only this part (repeatable)")
    _backend_args(p)
    p.add_argument("--seeds", type=_seeds, help="override the seeds, e.g. 0,1,2")
    p.add_argument("--name", help="override the experiment name (run folder)")
    p.add_argument("--fly", choices=["auto", "yes", "no"], default="auto",
                   help="fly the result in the MAVLink emulator when the config has [flight]")
    _progress_arg(p)
    p.set_defaults(handler=run)
    p = esub.add_parser("sweep", help="run a grid of config variants; writes "
                        "runs/NAME-sweep/ with one summary table")
    p.add_argument("config", help="experiment TOML")
    p.add_argument("--param", action="append", required=True, metavar="KEY=V1,V2",
                   help="a swept value list, e.g. stages.isar_one.alpha=1e-3,1e-2,1e-1 "
                        "(repeatable: the grid is the product)")
    p.add_argument("--out", default="runs", help="parent folder of the sweep (default runs/)")
    p.add_argument("--only", action="append", help="run only this part (repeatable)")
    _backend_args(p)
    p.add_argument("--seeds", type=_seeds, help="override the seeds of every variant, e.g. 0,1,2")
    _progress_arg(p)
    p.set_defaults(handler=run_sweep)
    p = esub.add_parser("report", help="re-write report.md and plots of a run (--partial: "
                        "an interim report of one still going)")
    p.add_argument("config", help="experiment TOML")
    p.add_argument("--out", default="runs")
    p.add_argument("--only", action="append")
    p.add_argument("--seeds", type=_seeds, help="the seeds to report, when the run used "
                   "--seeds (e.g. 0,1,2,3,4); default: the config's")
    p.add_argument("--name", help="the run folder's name, when the run used --name")
    p.add_argument("--partial", action="store_true",
                   help="count units that have started but not finished at the episode they "
                        "have reached (censored there if they have not converged yet); the "
                        "report is marked interim")
    p.set_defaults(handler=run_report)
    p = esub.add_parser("table", help="write README's results table from "
                        "docs/results/*/summary.json (--check: only compare)")
    from geonav.experiments.table import add_arguments

    add_arguments(p)
    p.set_defaults(handler=run_table)


def _progress_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bars or lines (unit failures and retries, and the "
                        "result, are still printed)")


def _backend_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--jobs", type=positive_int, default=None,
                   help="units run in parallel (default: [backend] jobs; local 2, ray: the "
                        "cluster's CPUs)")
    p.add_argument("--backend", choices=["local", "ray"], default=None,
                   help="where units run (default: [backend] kind, else local)")
    p.add_argument("--address", default=None,
                   help="Ray cluster: auto, ray://HOST:10001 or HOST:6379 (implies --backend "
                        "ray)")
    p.add_argument("--max-retries", type=nonneg_int, default=None,
                   help="reruns of a unit whose worker died (default: [backend] max_retries, 2)")


def _with_backend(cfg, args: argparse.Namespace):
    import dataclasses

    spec = cfg.backend
    changes: dict = {}
    if args.backend is not None:
        changes["kind"] = args.backend
    if args.address is not None:
        changes["kind"] = changes.get("kind", "ray")
        changes["address"] = args.address
    if args.jobs is not None:
        changes["jobs"] = args.jobs
    if args.max_retries is not None:
        changes["max_retries"] = args.max_retries
    if changes.get("kind", spec.kind) == "local" and changes.get("address"):
        from geonav.errors import ConfigError

        raise ConfigError("--address names a Ray cluster: use it with --backend ray")
    return dataclasses.replace(cfg, backend=dataclasses.replace(spec, **changes))


def _overrides(args: argparse.Namespace) -> dict:
    o: dict = {}
    if getattr(args, "seeds", None):
        o["seeds"] = list(args.seeds)
    if getattr(args, "name", None):
        o["name"] = args.name
    return o


def run(args: argparse.Namespace) -> int:
    from geonav.cliutil import progress_bar
    from geonav.experiments.config import load_config
    from geonav.experiments.runner import run_experiment

    cfg = _with_backend(load_config(args.config, _overrides(args)), args)
    on_event, overall = _bars(cfg.name, args.no_progress)
    summary = run_experiment(cfg, args.out, only=args.only, on_event=on_event,
                             progress=progress_bar("inputs", args.no_progress))
    overall.close()
    root = Path(args.out) / cfg.name
    if summary.get("locked"):
        print(f"report not written: {len(summary['locked'])} unit(s) are being trained by "
              f"another run of {cfg.name} ({', '.join(summary['locked'])}); it writes "
              f"{root / 'report.md'} when it ends")
        return 1
    print(f"report: {root / 'report.md'}")
    for comp in summary.get("comparisons", []):
        parts = []
        for m, rec in comp["methods"].items():
            c = rec["convergence"]
            if c["median"] is not None:
                parts.append(f"{m} {c['median']:.0f}{'+' if c['median_censored'] else ''} ep")
        print(f"  {comp['name']}: " + ", ".join(parts))
    if _should_fly(cfg, args.fly, args.only):
        from geonav.experiments.flight import fly_result

        record = fly_result(cfg, root)
        print(f"flight: {record}")
    return 1 if summary.get("failed") else 0


def _should_fly(cfg: Any, fly: str, only: list[str] | None) -> bool:
    """``--fly auto`` flies the [flight] stage only when this run trains it (not when
    ``--only`` picks parts without it); ``yes`` always, ``no`` never."""
    if fly != "auto":
        return fly == "yes"
    if not cfg.flight:
        return False
    stage = cfg.flight.get("stage")
    if only and stage not in cfg.stages_for(only):
        print(f"flight: skipped ([flight] flies stage {stage!r}, which --only "
              f"{','.join(only)} does not train; --fly yes flies it anyway)")
        return False
    return True


def run_sweep(args: argparse.Namespace) -> int:
    from geonav.cliutil import progress_bar
    from geonav.experiments.sweep import run_sweep as sweep

    on_event, overall = _bars("sweep", args.no_progress)
    record = sweep(args.config, args.param, args.out, overrides=_overrides(args),
                   only=args.only, on_event=on_event,
                   progress=progress_bar("inputs", args.no_progress),
                   configure=lambda cfg: _with_backend(cfg, args))
    overall.close()
    print(f"sweep: {Path(record['folder']) / 'sweep.md'}")
    print(record["table"])
    return 1 if any(r["failed_units"] for r in record["rows"]) else 0


def _outcomes(name: str):
    """No progress (``--no-progress``): only what the user must know, a unit that failed
    or whose worker died."""
    from geonav import cliutil
    from geonav.cliutil import LineProgress
    from geonav.experiments.runner import UnitEvent

    class _Overall:
        def close(self) -> None:
            pass

    def on_event(ev: UnitEvent) -> None:
        if ev.unit is None or cliutil.QUIET:
            return
        key = f"{ev.run}:{ev.unit.key}" if ev.run and name == "sweep" else ev.unit.key
        if ev.status == "failed":
            LineProgress.write(f"{name}: unit {key} failed: {ev.message}")
        elif ev.status == "retry":
            LineProgress.write(f"{name}: unit {key}: worker died, retrying from its last "
                               "checkpoint")

    return on_event, _Overall()


def _lines(name: str):
    """Unit progress for logs: a line per unit start/end and a summary every 30 s."""
    from geonav.cliutil import LineProgress
    from geonav.experiments.runner import UnitEvent

    lines = LineProgress()
    running: dict[str, tuple[int, int]] = {}

    class _Overall:
        def close(self) -> None:
            pass

    def on_event(ev: UnitEvent) -> None:
        if ev.unit is None:
            return
        key = f"{ev.run}:{ev.unit.key}" if ev.run and name == "sweep" else ev.unit.key
        if ev.status == "started":
            running[key] = (0, ev.budget)
            LineProgress.write(f"{name}: unit {key} started ({ev.done_units}/{ev.total_units} "
                               "done)")
        elif ev.status == "progress":
            running[key] = (ev.episodes, ev.budget)
        elif ev.status in ("done", "failed", "skipped"):
            running.pop(key, None)
            extra = f": {ev.message}" if ev.status == "failed" else ""
            LineProgress.write(f"{name}: unit {key} {ev.status} ({ev.done_units}/"
                               f"{ev.total_units} done){extra}")
        elif ev.status == "retry":
            LineProgress.write(f"{name}: unit {key}: worker died, retrying from its last "
                               "checkpoint")
        if running and lines.due():
            LineProgress.write(f"{name}: {ev.done_units}/{ev.total_units} units done; " +
                               ", ".join(f"{k} {e}/{b} ep" for k, (e, b) in running.items()))

    return on_event, _Overall()


def _bars(name: str, disable: bool = False):
    from tqdm import tqdm

    from geonav import cliutil
    from geonav.cliutil import is_terminal
    from geonav.experiments.runner import UnitEvent

    if disable or cliutil.QUIET:
        return _outcomes(name)
    if not is_terminal():
        return _lines(name)

    bars: dict[str, tqdm] = {}
    overall = tqdm(total=0, desc=f"{name}: units", position=0, unit="unit", disable=None)

    def on_event(ev: UnitEvent) -> None:
        overall.total = ev.total_units
        overall.n = ev.done_units
        overall.refresh()
        if ev.unit is None:
            return
        key = f"{ev.run}:{ev.unit.key}" if ev.run and name == "sweep" else ev.unit.key
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
        elif ev.status == "retry":
            tqdm.write(f"unit {key}: worker died, retrying from its last checkpoint")

    return on_event, overall


def run_report(args: argparse.Namespace) -> int:
    from geonav.cliutil import progress_bar
    from geonav.experiments.config import load_config
    from geonav.experiments.report import write_report
    from geonav.experiments.runner import prepare_inputs

    cfg = load_config(args.config, _overrides(args))
    root = Path(args.out) / cfg.name
    progress = progress_bar("report")
    scenes, tasks = prepare_inputs(cfg, root, progress)
    progress("units, curves and plots", 0.0)  # a line every ~30 s in a log while it runs
    summary = write_report(cfg, root, cfg.stages_for(args.only), scenes, tasks, {},
                           partial=args.partial, parts=args.only)
    progress("units, curves and plots", 1.0)
    print(f"report: {root / 'report.md'}")
    for key, why in summary["unreadable"].items():
        print(f"  left out, unreadable: {key}: {why}")
    return 1 if summary["unreadable"] else 0


def run_table(args: argparse.Namespace) -> int:
    from geonav.experiments.table import run as table

    return table(args)
