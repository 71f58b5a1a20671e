"""The transfer experiment runner.

``run_experiment(config, out_root)`` prepares the scenes and task sets, then
runs every (stage, seed) unit through a :class:`~geonav.experiments.backend.Backend`
as soon as its parent unit (``init``) is done, and finally writes
``summary.json`` and ``report.md`` with curves and tables.

Run folder ``runs/NAME/``::

    config.json                  resolved config
    scenes/<key>/                scene packages made on the fly
    tasks/<key>.json             task sets made on the fly
    units/<stage>/seed-<s>/      one training run: config.json, metrics.csv,
                                 checkpoints/, progress.json, result.json (when done),
                                 .lock (held while it trains), error.txt (its traceback,
                                 when it raised), retries.json (when its worker died)
    summary.json, report.md, *.png

Resume: rerunning skips units with a ``result.json`` and restarts unfinished
ones, which continue from their last checkpoint (the trainers' resume; metric
rows logged after that checkpoint are dropped first). The same happens within
a run when a unit's worker dies: it is resubmitted up to ``max_retries``
times. A unit that raises is recorded as failed with its traceback and the
other units go on (those that start from it are skipped).

Every unit holds its folder's lock while it trains, so two runs of the same
experiment (or an orphaned worker of a killed run) never train one unit twice
at once: the second one fails with :class:`UnitLocked` on those units and leaves
``summary.json`` and ``report.md`` to the first (which writes them when it ends).

``result.json`` stores its paths relative to the run folder, so a run folder that is
copied or moved is reported from where it is (:func:`read_result`).

This module owns the scheduling: opening a run (and refusing one of another config),
submitting ready units to the backend, collecting, retrying and sharing them, and
the summaries. The unit folder's records, result.json and lock live in
:mod:`geonav.experiments.units`, the making of scenes and task sets in
:mod:`geonav.experiments.inputs`; their names are re-exported here.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import traceback
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geonav.errors import ConfigError
from geonav.experiments.backend import Backend, WorkerLost, make_backend
from geonav.experiments.config import ExperimentConfig
from geonav.experiments.inputs import coverage_needs, make_taskset, prepare_inputs, task_difficulty
from geonav.experiments.report import write_report
from geonav.experiments.units import (
    ERROR,
    LOCK,
    LOCK_WAIT_S,
    PROGRESS,
    RESULT,
    RESULT_PATHS,
    RETRIES,
    SHARED_INPUTS,
    Unit,
    UnitEvent,
    UnitLocked,
    read_json,
    read_lock,
    read_result,
    run_group,
    run_root,
    run_unit,
    unit_dir,
    unit_lock,
    write_json,
    write_result,
)

#: Names that moved to :mod:`~geonav.experiments.units` and
#: :mod:`~geonav.experiments.inputs`, still importable from here.
__all__ = [
    "ERROR", "LOCK", "LOCK_WAIT_S", "PACKABLE_ALGOS", "PROGRESS", "RESULT", "RESULT_PATHS",
    "RETRIES", "SHARED_INPUTS", "Unit", "UnitEvent", "UnitLocked", "coverage_needs",
    "make_taskset", "packs", "prepare_inputs", "read_lock", "read_result", "run_experiment",
    "run_experiments", "run_group", "run_root", "run_unit", "task_difficulty", "unit_dir",
    "unit_lock", "write_result",
]

log = logging.getLogger(__name__)


PACKABLE_ALGOS = ("a3c", "ppo", "isar", "savn")
"""Algorithms whose train-mode units of one stage a run packs (``pack = true``)."""


def packs(stage: Any) -> bool:
    """Whether the runner runs the seeds of ``stage`` as one packed group: the stage option
    ``pack = true`` (off by default), mode 'train', the batched engine, a packable
    algorithm. A stage that asks for it but cannot is run unit by unit, with a warning."""
    if not stage.options.get("pack", False):
        return False
    why = None
    if stage.mode != "train":
        why = f"mode {stage.mode!r} (packing applies to mode 'train')"
    elif stage.options.get("engine", "batched") != "batched":
        why = "engine 'async' (packing needs the batched engine)"
    elif stage.algo not in PACKABLE_ALGOS:
        why = f"algo {stage.algo!r} (packable: {', '.join(PACKABLE_ALGOS)})"
    if why is not None:
        log.warning("stage with pack = true runs unit by unit: %s", why)
        return False
    return True


@dataclass
class _Run:
    """One experiment being run: its config, folder, inputs and unit states."""

    cfg: ExperimentConfig
    root: Path
    stage_keys: list[str]
    units: list[Unit]
    scenes: dict[str, str]
    tasks: dict[str, str]
    done: dict[Unit, dict[str, Any]] = field(default_factory=dict)
    failed: dict[Unit, str] = field(default_factory=dict)
    retries: dict[Unit, int] = field(default_factory=dict)
    only: list[str] | None = None
    locked: dict[Unit, str] = field(default_factory=dict)
    """Units another live run is training (refused by their locks): this run is not the
    one that writes the report."""


def _open_run(cfg: ExperimentConfig, out_root: str | os.PathLike[str], only: list[str] | None,
              progress: Callable[[str, float], None] | None,
              shared_inputs: Path | None = None) -> _Run:
    root = Path(out_root).resolve() / cfg.name
    root.mkdir(parents=True, exist_ok=True)
    previous = read_json(root / "config.json")
    resolved = cfg.to_dict()
    stage_keys = cfg.stages_for(only)
    if previous is not None and not _same_part(_experiment_part(previous, stage_keys),
                                               _experiment_part(resolved, stage_keys)):
        raise ConfigError(f"{root} holds a run of a different config; use another name or "
                          "remove the folder")
    _refuse_orphan_units(root, previous, stage_keys)
    write_json(root / "config.json", resolved)
    scenes, tasks = prepare_inputs(cfg, root, progress, shared_inputs,
                                   stage_keys if only else None)
    units = [Unit(s, seed) for s in stage_keys for seed in cfg.seeds]
    return _Run(cfg, root, stage_keys, units, scenes, tasks, only=only)


def run_experiment(
    cfg: ExperimentConfig,
    out_root: str | os.PathLike[str] = "runs",
    *,
    only: list[str] | None = None,
    jobs: int | None = None,
    backend: Backend | None = None,
    max_retries: int | None = None,
    on_event: Callable[[UnitEvent], None] | None = None,
    progress: Callable[[str, float], None] | None = None,
    report: bool = True,
) -> dict[str, Any]:
    """Run (or resume) an experiment; returns the summary.

    Args:
        cfg: the experiment.
        out_root: parent folder; the run goes to ``out_root/cfg.name``.
        only: part names to run (``[[compare]] part``); None runs everything.
        jobs: concurrent units (default: ``[backend] jobs``, else 2 locally, else the
            cluster's capacity on Ray).
        backend: where units run (default: the config's ``[backend]``; shut down at the end).
        max_retries: retries of a unit whose worker died (default: ``[backend] max_retries``).
        on_event: unit-level progress callback.
        progress: input-preparation progress callback.
        report: write summary.json and report.md at the end.
    """
    return run_experiments([cfg], out_root, only=only, jobs=jobs, backend=backend,
                           max_retries=max_retries, on_event=on_event, progress=progress,
                           report=report)[0]


def run_experiments(
    cfgs: list[ExperimentConfig],
    out_root: str | os.PathLike[str] = "runs",
    *,
    only: list[str] | None = None,
    jobs: int | None = None,
    backend: Backend | None = None,
    max_retries: int | None = None,
    on_event: Callable[[UnitEvent], None] | None = None,
    progress: Callable[[str, float], None] | None = None,
    report: bool = True,
    shared_inputs: str | os.PathLike[str] | None = None,
) -> list[dict[str, Any]]:
    """Run several experiments (a sweep's variants) through one backend at once.

    Units of all the experiments share the backend's slots; each experiment keeps its
    own folder ``out_root/cfg.name`` and report. A unit that is the very same training
    in several of them (same stage, task set, options and seed, and same parents) is
    trained once; the others' unit folders link to it. Returns the summaries in order. The
    backend and the retry budget come from the first config unless given.
    ``shared_inputs``: one folder for the scenes and task sets of all of them (see
    :func:`prepare_inputs`).
    """
    if not cfgs:
        return []
    spec = cfgs[0].backend
    if backend is None:  # first: a missing extra or cluster fails before any work
        backend = make_backend(spec.kind, jobs=jobs if jobs is not None else spec.jobs,
                               address=spec.address, cpus_per_unit=spec.cpus_per_unit,
                               gpus_per_unit=spec.gpus_per_unit)
    try:
        shared = None if shared_inputs is None else Path(shared_inputs).resolve()
        runs = [_open_run(cfg, out_root, only, progress, shared) for cfg in cfgs]
    except BaseException:
        backend.shutdown(cancel=True)
        raise
    retries_allowed = spec.max_retries if max_retries is None else max_retries
    total = sum(len(r.units) for r in runs)
    for run in runs:
        for u in run.units:
            r = read_result(unit_dir(run.root, u))
            if r is not None:
                run.done[u] = r
                _emit(on_event, UnitEvent(u, "skipped", r.get("episodes", 0),
                                          r.get("episodes", 0), _n_done(runs), total,
                                          run=run.cfg.name))
    running: dict[Future, tuple[_Run, Unit | tuple[Unit, ...]]] = {}
    shared = _share(runs)
    try:
        for run in runs:
            backend.attach(run.root)
        while True:
            _submit_ready(runs, backend, running, on_event, total, shared)
            if not running:
                break
            finished, _ = wait(list(running), timeout=1.0, return_when=FIRST_COMPLETED)
            for fut in finished:
                run, what = running.pop(fut)
                if isinstance(what, tuple):
                    _collect_group(run, what, fut, retries_allowed, on_event, runs, total)
                else:
                    _collect(run, what, fut, retries_allowed, on_event, _n_done(runs), total)
            for run, what in running.values():
                for u in what if isinstance(what, tuple) else (what,):
                    _progress(run, u, on_event, runs, total)
    except BaseException:
        backend.shutdown(cancel=True)
        raise
    backend.shutdown()
    return _summaries(runs, report)


def _progress(run: _Run, u: Unit, on_event: Callable[[UnitEvent], None] | None,
              runs: list[_Run], total: int) -> None:
    p = read_json(unit_dir(run.root, u) / PROGRESS)
    if p:
        _emit(on_event, UnitEvent(u, "progress", p.get("episodes", 0),
                                  run.cfg.stages[u.stage].episodes, _n_done(runs), total,
                                  run=run.cfg.name))


def _summaries(runs: list[_Run], report: bool) -> list[dict[str, Any]]:
    summaries = []
    for run in runs:
        summary: dict[str, Any] = {"name": run.cfg.name,
                                   "failed": {u.key: m for u, m in run.failed.items()}}
        if run.locked:
            # Another live run of this experiment trains these units and writes the
            # report when it ends; this run's view (its units "failed") would be false.
            summary["locked"] = {u.key: m for u, m in run.locked.items()}
            log.warning("%s: %d unit(s) are being trained by another run of this experiment; "
                        "report.md and summary.json are left to that run", run.cfg.name,
                        len(run.locked))
            summary["retries"] = {u.key: n for u, n in run.retries.items()}
            summaries.append(summary)
            continue
        if report:
            summary = write_report(run.cfg, run.root, run.stage_keys, run.scenes, run.tasks,
                                   run.failed, parts=run.only)
        summary["retries"] = {u.key: n for u, n in run.retries.items()}
        written = read_json(run.root / "summary.json") if report else None
        if written is not None:
            write_json(run.root / "summary.json", {**written, "retries": summary["retries"]})
        summaries.append(summary)
    return summaries


def _n_done(runs: list[_Run]) -> int:
    return sum(len(r.done) for r in runs)


def _fingerprint(run: _Run, u: Unit) -> str:
    """What makes a unit's training: its payload but the folders, and its parent's."""
    stage = run.cfg.stages[u.stage]
    parent = None if stage.init is None else Unit(stage.init, u.seed)
    payload = _payload(run.cfg, run.root, u, run.scenes, run.tasks,
                       {} if parent is None else {parent: {"checkpoint": None}})
    payload.pop("out_dir")
    payload["init_checkpoint"] = None if parent is None else _fingerprint(run, parent)
    blob = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()


def _share(runs: list[_Run]) -> dict[tuple[int, Unit], tuple[_Run, Unit]]:
    """Units of later runs that are the very same training as one of an earlier run
    (a sweep point that changes only a later stage): (run id, unit) -> its owner."""
    owners: dict[str, tuple[_Run, Unit]] = {}
    shared: dict[tuple[int, Unit], tuple[_Run, Unit]] = {}
    for run in runs:
        for u in run.units:
            fp = _fingerprint(run, u)
            owner = owners.setdefault(fp, (run, u))
            here = unit_dir(run.root, u)
            if owner[0] is run or (here.exists() and not here.is_symlink()):
                continue  # its own folder (e.g. trained before sharing): keep it
            shared[(id(run), u)] = owner
    return shared


def _adopt(run: _Run, u: Unit, owner: tuple[_Run, Unit]) -> None:
    """Make ``u``'s folder a link to its owner's (done) folder and take its result."""
    orun, ou = owner
    here, there = unit_dir(run.root, u), unit_dir(orun.root, ou)
    if not here.is_symlink():
        here.parent.mkdir(parents=True, exist_ok=True)
        here.symlink_to(os.path.relpath(there, here.parent), target_is_directory=True)
    run.done[u] = orun.done[ou]


def _submit_ready(runs: list[_Run], backend: Backend,
                  running: dict[Future, tuple[_Run, Unit | tuple[Unit, ...]]],
                  on_event: Callable[[UnitEvent], None] | None, total: int,
                  shared: dict[tuple[int, Unit], tuple[_Run, Unit]]) -> None:
    busy = {(id(r), u) for r, what in running.values()
            for u in (what if isinstance(what, tuple) else (what,))}
    for run in runs:
        for u in run.units:
            if u in run.done or u in run.failed or (id(run), u) in busy:
                continue
            owner = shared.get((id(run), u))
            if owner is not None:  # trained once, by its owner
                orun, ou = owner
                if ou in orun.done:
                    _adopt(run, u, owner)
                    _emit(on_event, UnitEvent(u, "done", run.done[u].get("episodes", 0),
                                              run.cfg.stages[u.stage].episodes,
                                              _n_done(runs), total,
                                              f"the same unit as {orun.cfg.name}:{ou.key}",
                                              run=run.cfg.name))
                elif ou in orun.failed:
                    run.failed[u] = f"the same unit as {orun.cfg.name}:{ou.key}, which failed"
                continue
            if len(running) >= backend.slots:
                return
            stage = run.cfg.stages[u.stage]
            if stage.init is not None:
                pu = Unit(stage.init, u.seed)
                if pu in run.locked:
                    run.failed[u] = f"parent {pu.key} is being trained by another run"
                    continue
                if pu in run.failed:
                    run.failed[u] = f"parent {pu.key} failed"
                    continue
                if pu not in run.done:
                    continue
            if packs(stage):
                group = _ready_group(run, u, busy, shared)
                if group is None:
                    continue
                if len(group) > 1:
                    payloads = [_payload(run.cfg, run.root, m, run.scenes, run.tasks, run.done)
                                for m in group]
                    fut = backend.submit(run_group, payloads,
                                         resources={"cpus": max(1, stage.workers)})
                    running[fut] = (run, group)
                    busy.update((id(run), m) for m in group)
                    for m in group:
                        _emit(on_event, UnitEvent(m, "started", 0, stage.episodes,
                                                  _n_done(runs), total,
                                                  f"packed with {len(group) - 1} more",
                                                  run=run.cfg.name))
                    continue
            payload = _payload(run.cfg, run.root, u, run.scenes, run.tasks, run.done)
            fut = backend.submit(run_unit, payload, resources={"cpus": max(1, stage.workers)})
            running[fut] = (run, u)
            _emit(on_event, UnitEvent(u, "started", 0, stage.episodes, _n_done(runs), total,
                                      run=run.cfg.name))


def _ready_group(run: _Run, u: Unit, busy: set[tuple[int, Unit]],
                 shared: dict[tuple[int, Unit], tuple[_Run, Unit]]) -> tuple[Unit, ...] | None:
    """The units of ``u``'s stage still to train, once all of them can start (None while a
    member's parent is still training); done, failed and shared units are left out."""
    stage = run.cfg.stages[u.stage]
    group = []
    for m in run.units:
        if m.stage != u.stage or m in run.done or m in run.failed or \
                (id(run), m) in busy or (id(run), m) in shared:
            continue
        if stage.init is not None and Unit(stage.init, m.seed) not in run.done:
            if Unit(stage.init, m.seed) in run.failed:
                continue
            return None
        group.append(m)
    return tuple(group)


def _collect_group(run: _Run, group: tuple[Unit, ...], fut: Future, retries_allowed: int,
                   on_event: Callable[[UnitEvent], None] | None, runs: list[_Run],
                   total: int) -> None:
    """Record a finished packed group: each member done, or the group retried (its worker
    died; each member resumes from its own checkpoint, a member that finished is not
    re-run) or failed (it raised)."""
    try:
        results = fut.result()["members"]
    except WorkerLost as err:
        n = max(run.retries.get(m, 0) for m in group) + 1
        for m in group:
            run.retries[m] = n
            out = unit_dir(run.root, m)
            out.mkdir(parents=True, exist_ok=True)
            write_json(out / RETRIES, {"worker_lost": n, "last": str(err), "packed": True})
            finished = read_result(out)
            if finished is not None:  # finished before the worker died
                run.done[m] = finished
            elif n > retries_allowed:
                run.failed[m] = (f"its packed group's worker died {n} times (max_retries = "
                                 f"{retries_allowed}): {err}")
        log.warning("packed group %s: its worker died (%s); retry %d of %d from the members' "
                    "checkpoints", [m.key for m in group], err, n, retries_allowed)
        return
    except UnitLocked as err:  # a member is being trained by another run: none started
        for m in group:
            run.failed[m] = run.locked[m] = str(err)
            _emit(on_event, UnitEvent(m, "failed", 0, 0, _n_done(runs), total,
                                      run.failed[m], run=run.cfg.name))
        log.error("packed group %s not started: %s", [m.key for m in group], err)
        return
    except Exception as err:  # noqa: BLE001 - the group's own failure, reported
        for m in group:
            run.failed[m] = f"{type(err).__name__}: {err} (packed group; traceback: " \
                            f"{unit_dir(run.root, m) / ERROR})"
            _emit(on_event, UnitEvent(m, "failed", 0, 0, _n_done(runs), total,
                                      run.failed[m], run=run.cfg.name))
        log.error("packed group %s failed: %s", [m.key for m in group], err)
        return
    for m, r in zip(group, results, strict=True):
        run.done[m] = r
        _emit(on_event, UnitEvent(m, "done", r.get("episodes", 0),
                                  run.cfg.stages[m.stage].episodes, _n_done(runs), total,
                                  run=run.cfg.name))


def _collect(run: _Run, u: Unit, fut: Future, retries_allowed: int,
             on_event: Callable[[UnitEvent], None] | None, n_done: int, total: int) -> None:
    """Record a finished unit: done, retried (its worker died) or failed (it raised)."""
    out = unit_dir(run.root, u)
    budget = run.cfg.stages[u.stage].episodes
    try:
        run.done[u] = fut.result()
    except WorkerLost as err:
        n = run.retries[u] = run.retries.get(u, 0) + 1
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / RETRIES, {"worker_lost": n, "last": str(err)})
        if n <= retries_allowed:
            log.warning("unit %s: its worker died (%s); retry %d of %d from its last "
                        "checkpoint", u.key, err, n, retries_allowed)
            _emit(on_event, UnitEvent(u, "retry", 0, budget, n_done, total, str(err),
                                      run=run.cfg.name))
            return
        run.failed[u] = f"its worker died {n} times (max_retries = {retries_allowed}): {err}"
    except UnitLocked as err:
        run.failed[u] = run.locked[u] = str(err)
    except Exception as err:  # noqa: BLE001 - a unit's own failure, reported; the rest goes on
        trace = out / ERROR
        if not trace.exists():  # raised outside run_unit (e.g. by the backend)
            out.mkdir(parents=True, exist_ok=True)
            trace.write_text("".join(traceback.format_exception(err)))
        run.failed[u] = f"{type(err).__name__}: {err} (traceback: {trace})"
    else:
        _emit(on_event, UnitEvent(u, "done", run.done[u].get("episodes", 0), budget,
                                  n_done + 1, total, run=run.cfg.name))
        return
    log.error("unit %s failed: %s", u.key, run.failed[u])
    _emit(on_event, UnitEvent(u, "failed", 0, 0, n_done, total, run.failed[u],
                              run=run.cfg.name))


def _experiment_part(d: dict[str, Any], stages: list[str] | None = None) -> Any:
    """What must match to resume: everything that changes the runs' meaning; with
    ``stages``, only those stages, their task sets and scenes (editing a part that is not
    being run does not block resuming the others)."""
    if stages is None:
        return {k: d.get(k) for k in ("scenes", "tasks", "stages", "convergence")}
    st = {k: (d.get("stages") or {}).get(k) for k in stages}
    tk = sorted({v["tasks"] for v in st.values() if v})
    tasks = {k: (d.get("tasks") or {}).get(k) for k in tk}
    sc = sorted({v["scene"] for v in tasks.values() if v})
    return {"stages": st, "tasks": tasks, "scenes": {k: (d.get("scenes") or {}).get(k)
                                                     for k in sc},
            "convergence": d.get("convergence")}


def _same_part(before: dict[str, Any], now: dict[str, Any]) -> bool:
    """Whether a run's part may resume under the config now: every stage, task set and
    scene it held is unchanged. A name the run's config did not have (a part added to the
    config since) is new, not a change."""
    for k, v in now.items():
        old = before.get(k)
        if isinstance(v, dict) and isinstance(old, dict) and k != "convergence":
            if any(old.get(n) is not None and not _same_spec(old[n], spec)
                   for n, spec in v.items()):
                return False
        elif old != v:
            return False
    return True


def _same_spec(old: Any, now: Any) -> bool:
    """Equal specs, where a key the older config.json lacks counts as unset (None): a
    field added to geonav later, left at its default, does not block resuming."""
    if isinstance(old, dict) and isinstance(now, dict):
        return all(old.get(k) == now.get(k) for k in set(old) | set(now))
    return bool(old == now)


def _refuse_orphan_units(root: Path, previous: dict[str, Any] | None,
                         stage_keys: list[str]) -> None:
    """A stage the folder's config.json does not name is new to the folder only if it has
    no units there: config.json is rewritten by every run, so units of a stage that was
    dropped from the config, run around, and added again may come from other settings."""
    known = set((previous or {}).get("stages") or {})
    for s in stage_keys:
        d = root / "units" / s
        if s not in known and d.is_dir() and any(d.iterdir()):
            raise ConfigError(
                f"{d} holds runs of stage {s!r}, which this folder's config.json does not "
                "name (was it dropped from the config and added again?), so their settings "
                "cannot be checked; remove that folder to rerun the stage, or use another "
                "name")


def _payload(cfg: ExperimentConfig, root: Path, u: Unit, scenes: dict[str, str],
             tasks: dict[str, str], done: dict[Unit, dict[str, Any]]) -> dict[str, Any]:
    stage = cfg.stages[u.stage]
    tspec = cfg.tasks[stage.tasks]
    init_ckpt = None
    if stage.init is not None:
        init_ckpt = done[Unit(stage.init, u.seed)]["checkpoint"]
        if stage.init_alt_m is not None and init_ckpt is not None:
            init_ckpt = _level_checkpoint(init_ckpt, stage.init_alt_m)
    extra = {} if stage.init_alt_m is None else {"init_alt_m": stage.init_alt_m}
    return dict(**extra,
        stage=u.stage, mode=stage.mode, algo=stage.algo, episodes=stage.episodes,
        workers=stage.workers, options=dict(stage.options), seed=u.seed,
        scene=scenes[tspec.scene], tasks=tasks[stage.tasks], init_checkpoint=init_ckpt,
        out_dir=str(unit_dir(root, u)), convergence=dict(
            window=cfg.convergence.window, threshold=cfg.convergence.threshold,
            hold=cfg.convergence.hold, eval_threshold=cfg.convergence.eval_threshold),
        eval_starts=cfg.eval_starts,
    )


def _level_checkpoint(final_ckpt: str, alt_m: float) -> str:
    """The final policy of one level of a finished curriculum unit, from its curriculum.json
    (the unit's folder is two above its final checkpoint)."""
    unit = Path(final_ckpt).parent.parent
    state = read_json(unit / "curriculum.json") or {}
    for i, s in enumerate(state.get("stages", [])):
        if float(s["alt_m"]) == float(alt_m):
            path = unit / f"stage_{i}_{float(alt_m):g}m" / "checkpoints" / "final.pt"
            if path.exists():
                return str(path)
    raise ConfigError(f"{unit}: the curriculum has no finished {alt_m:g} m level to start "
                      "from (init_alt_m)")


def _emit(cb: Callable[[UnitEvent], None] | None, ev: UnitEvent) -> None:
    if cb is not None:
        cb(ev)
