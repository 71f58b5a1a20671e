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
                                 checkpoints/, progress.json, result.json (when done)
    summary.json, report.md, *.png

Resume: rerunning skips units with a ``result.json`` and restarts unfinished
ones, which continue from their last checkpoint (the trainers' resume).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geonav.errors import ConfigError, GeonavError
from geonav.experiments.backend import Backend, LocalBackend
from geonav.experiments.config import ExperimentConfig, TaskSpec

log = logging.getLogger(__name__)

RESULT = "result.json"
PROGRESS = "progress.json"


@dataclass(frozen=True)
class Unit:
    """One stage for one seed."""

    stage: str
    seed: int

    @property
    def key(self) -> str:
        return f"{self.stage}/seed-{self.seed}"


@dataclass
class UnitEvent:
    """Progress of the experiment, for the CLI's bars."""

    unit: Unit | None
    status: str  # "skipped" | "started" | "progress" | "done" | "failed"
    episodes: int = 0
    budget: int = 0
    done_units: int = 0
    total_units: int = 0
    message: str = ""


def unit_dir(root: Path, unit: Unit) -> Path:
    return root / "units" / unit.stage / f"seed-{unit.seed}"


def prepare_inputs(cfg: ExperimentConfig, root: Path,
                   progress: Callable[[str, float], None] | None = None
                   ) -> tuple[dict[str, str], dict[str, str]]:
    """Make (or reuse) the scene packages and task sets; returns key -> path maps."""
    from geonav.demo import ensure_scene

    scenes: dict[str, str] = {}
    for key, spec in cfg.scenes.items():
        if spec.path:
            scenes[key] = str(Path(spec.path).resolve())
        else:
            out = root / "scenes" / key
            ensure_scene(out, key, spec.synthetic or "residential", spec.seed, spec.size_m,
                         spec.gsd_m, progress=progress)
            scenes[key] = str(out.resolve())
    tasks: dict[str, str] = {}
    for key, tspec in cfg.tasks.items():
        if tspec.path:
            tasks[key] = str(Path(tspec.path).resolve())
            continue
        out = root / "tasks" / f"{key}.json"
        if not out.exists():
            from geonav.difficulty import taskset_difficulty
            from geonav.scene import Scene

            ts = make_taskset(tspec, scenes[tspec.scene])
            ts.meta["difficulty"] = taskset_difficulty(ts, Scene.open(scenes[tspec.scene]))
            ts.save(out)
        tasks[key] = str(out.resolve())
    from geonav.experiments.config import check_noise

    check_noise(cfg, {k: task_difficulty(scenes[cfg.tasks[k].scene], p)["random_walk_sr"]
                      for k, p in tasks.items()})
    return scenes, tasks


def task_difficulty(scene_path: str, tasks_path: str) -> dict[str, Any]:
    """The task set's chance figures (geonav.difficulty), computed once and kept in its
    JSON ``meta["difficulty"]`` (user-supplied task files are left untouched)."""
    from geonav.difficulty import taskset_difficulty
    from geonav.scene import Scene
    from geonav.tasks import TaskSet

    ts = TaskSet.load(tasks_path)
    if isinstance(ts.meta.get("difficulty"), dict):
        return ts.meta["difficulty"]
    return taskset_difficulty(ts, Scene.open(scene_path))


def make_taskset(spec: TaskSpec, scene_path: str):
    """The task set a :class:`TaskSpec` describes, on its scene."""
    from geonav.camera import Camera
    from geonav.scene import Scene
    from geonav.tasks import sample_meta_tasks, whole_scene_tasks

    scene = Scene.open(scene_path)
    camera = Camera(spec.obs_size_px)
    if spec.kind == "meta":
        return sample_meta_tasks(scene, spec.count, size_m=spec.size_m or 150.0,
                                 alt_m=spec.alt_m, step_m=spec.step_m, max_steps=spec.max_steps,
                                 seed=spec.seed, camera=camera, margin_alt_m=spec.margin_alt_m)
    return whole_scene_tasks(scene, spec.alts_m, step_m=spec.step_m, max_steps=spec.max_steps,
                             seed=spec.seed, size_m=spec.size_m, camera=camera)


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def run_unit(payload: dict[str, Any]) -> dict[str, Any]:
    """Run one unit in this process (the function backends execute)."""
    from geonav.experiments.stages import execute_stage

    out = Path(payload["out_dir"])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    result = execute_stage(payload)
    result["wall_s_this_session"] = time.time() - t0
    _write_json(out / RESULT, result)
    return result


def run_experiment(
    cfg: ExperimentConfig,
    out_root: str | os.PathLike[str] = "runs",
    *,
    only: list[str] | None = None,
    jobs: int = 1,
    backend: Backend | None = None,
    on_event: Callable[[UnitEvent], None] | None = None,
    progress: Callable[[str, float], None] | None = None,
    report: bool = True,
) -> dict[str, Any]:
    """Run (or resume) an experiment; returns the summary.

    Args:
        cfg: the experiment.
        out_root: parent folder; the run goes to ``out_root/cfg.name``.
        only: part names to run (``[[compare]] part``); None runs everything.
        jobs: concurrent units for the default local backend.
        backend: where units run (default: :class:`LocalBackend` with ``jobs``).
        on_event: unit-level progress callback.
        progress: input-preparation progress callback.
        report: write summary.json and report.md at the end.
    """
    root = Path(out_root).resolve() / cfg.name
    root.mkdir(parents=True, exist_ok=True)
    previous = _read_json(root / "config.json")
    resolved = cfg.to_dict()
    if previous is not None and _experiment_part(previous) != _experiment_part(resolved):
        raise ConfigError(f"{root} holds a run of a different config; use another name or "
                          "remove the folder")
    _write_json(root / "config.json", resolved)
    scenes, tasks = prepare_inputs(cfg, root, progress)
    stage_keys = cfg.stages_for(only)
    units = [Unit(s, seed) for s in stage_keys for seed in cfg.seeds]
    done: dict[Unit, dict[str, Any]] = {}
    for u in units:
        r = _read_json(unit_dir(root, u) / RESULT)
        if r is not None:
            done[u] = r
            _emit(on_event, UnitEvent(u, "skipped", r.get("episodes", 0), r.get("episodes", 0),
                                      len(done), len(units)))
    backend = backend or LocalBackend(jobs)
    running: dict[Future, Unit] = {}
    failed: dict[Unit, str] = {}
    try:
        while True:
            for u in units:
                if u in done or u in failed or u in running.values():
                    continue
                if len(running) >= backend.slots:
                    break
                parent = cfg.stages[u.stage].init
                if parent is not None:
                    pu = Unit(parent, u.seed)
                    if pu in failed:
                        failed[u] = f"parent {pu.key} failed"
                        continue
                    if pu not in done:
                        continue
                payload = _payload(cfg, root, u, scenes, tasks, done)
                running[backend.submit(run_unit, payload)] = u
                _emit(on_event, UnitEvent(u, "started", 0, cfg.stages[u.stage].episodes,
                                          len(done), len(units)))
            if not running:
                break
            finished, _ = wait(list(running), timeout=1.0, return_when=FIRST_COMPLETED)
            for fut in finished:
                u = running.pop(fut)
                try:
                    done[u] = fut.result()
                    _emit(on_event, UnitEvent(u, "done", done[u].get("episodes", 0),
                                              cfg.stages[u.stage].episodes, len(done),
                                              len(units)))
                except (GeonavError, RuntimeError, OSError, ValueError) as err:
                    failed[u] = f"{type(err).__name__}: {err}"
                    log.error("unit %s failed: %s", u.key, err)
                    _emit(on_event, UnitEvent(u, "failed", 0, 0, len(done), len(units),
                                              failed[u]))
            for fut, u in running.items():
                p = _read_json(unit_dir(root, u) / PROGRESS)
                if p:
                    _emit(on_event, UnitEvent(u, "progress", p.get("episodes", 0),
                                              cfg.stages[u.stage].episodes, len(done),
                                              len(units)))
    except BaseException:
        backend.shutdown(cancel=True)
        raise
    backend.shutdown()
    summary: dict[str, Any] = {"name": cfg.name, "failed": {u.key: m for u, m in failed.items()}}
    if report:
        from geonav.experiments.report import write_report

        summary = write_report(cfg, root, stage_keys, scenes, tasks, failed)
    return summary


def _experiment_part(d: dict[str, Any]) -> Any:
    # What must match to resume: everything that changes the runs' meaning.
    return {k: d.get(k) for k in ("scenes", "tasks", "stages", "convergence")}


def _payload(cfg: ExperimentConfig, root: Path, u: Unit, scenes: dict[str, str],
             tasks: dict[str, str], done: dict[Unit, dict[str, Any]]) -> dict[str, Any]:
    stage = cfg.stages[u.stage]
    tspec = cfg.tasks[stage.tasks]
    init_ckpt = None
    if stage.init is not None:
        init_ckpt = done[Unit(stage.init, u.seed)]["checkpoint"]
    return dict(
        stage=u.stage, mode=stage.mode, algo=stage.algo, episodes=stage.episodes,
        workers=stage.workers, options=dict(stage.options), seed=u.seed,
        scene=scenes[tspec.scene], tasks=tasks[stage.tasks], init_checkpoint=init_ckpt,
        out_dir=str(unit_dir(root, u)), convergence=dict(
            window=cfg.convergence.window, threshold=cfg.convergence.threshold,
            hold=cfg.convergence.hold, eval_threshold=cfg.convergence.eval_threshold),
        eval_starts=cfg.eval_starts,
    )


def _emit(cb: Callable[[UnitEvent], None] | None, ev: UnitEvent) -> None:
    if cb is not None:
        cb(ev)
