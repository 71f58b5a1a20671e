"""The inputs of an experiment run: its scene packages and task sets, made or reused.

:func:`prepare_inputs` synthesises the scenes a config asks for (:mod:`geonav.demo`)
and samples its task sets (:func:`make_taskset`, with their chance figures from
:mod:`geonav.difficulty` kept in the task set's ``meta["difficulty"]``), in the run
folder or in a sweep's shared folder, and checks the config's noise floor against them.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from geonav.experiments.config import ExperimentConfig, TaskSpec, check_noise


def prepare_inputs(cfg: ExperimentConfig, root: Path,
                   progress: Callable[[str, float], None] | None = None,
                   shared_root: Path | None = None,
                   stages: list[str] | None = None,
                   ) -> tuple[dict[str, str], dict[str, str]]:
    """Make (or reuse) the scene packages and task sets; returns key -> path maps.

    ``shared_root`` (a sweep's folder): inputs go there under names that carry a hash
    of their spec, so variants with the same scene or task set share one copy.
    ``stages``: make only the task sets these stages train on, and their scenes (a run
    of some parts of a config does not synthesise the scenes of the others).
    """
    from geonav.demo import ensure_scene

    base = root if shared_root is None else shared_root

    def name(key: str, spec: Any, extra: str = "") -> str:
        if shared_root is None:
            return key
        d = asdict(spec)
        if d.get("max_blind", 0) is None:  # added later: unset keeps the older names
            d.pop("max_blind")
        blob = json.dumps([d, extra], sort_keys=True, default=str)
        return f"{key}-{hashlib.sha1(blob.encode()).hexdigest()[:8]}"

    task_keys = list(cfg.tasks) if stages is None else \
        sorted({cfg.stages[k].tasks for k in stages})
    scene_keys = list(cfg.scenes) if stages is None else \
        sorted({cfg.tasks[k].scene for k in task_keys})
    scenes: dict[str, str] = {}
    for key, spec in cfg.scenes.items():
        if key not in scene_keys:
            continue
        if spec.path:
            scenes[key] = str(Path(spec.path).resolve())
        else:
            out = base / "scenes" / name(key, spec)
            ensure_scene(out, key, spec.synthetic or "residential", spec.seed, spec.size_m,
                         spec.gsd_m, progress=progress,
                         needs=coverage_needs(cfg, key, task_keys))
            scenes[key] = str(out.resolve())
    tasks: dict[str, str] = {}
    for key, tspec in cfg.tasks.items():
        if key not in task_keys:
            continue
        if tspec.path:
            tasks[key] = str(Path(tspec.path).resolve())
            continue
        out = base / "tasks" / f"{name(key, tspec, scenes[tspec.scene])}.json"
        if not out.exists():
            from geonav.difficulty import taskset_difficulty
            from geonav.scene import Scene

            out.parent.mkdir(parents=True, exist_ok=True)
            ts = make_taskset(tspec, scenes[tspec.scene], progress)
            if progress is not None:
                progress(f"chance figures of {key}", 0.0)
            ts.meta["difficulty"] = taskset_difficulty(ts, Scene.open(scenes[tspec.scene]))
            if progress is not None:
                progress(f"chance figures of {key}", 1.0)
            ts.save(out)
        tasks[key] = str(out.resolve())
    check_noise(cfg, {k: task_difficulty(scenes[cfg.tasks[k].scene], p)
                      for k, p in tasks.items()})
    if progress is not None:
        progress("inputs ready", 1.0)
    return scenes, tasks


def coverage_needs(cfg: ExperimentConfig, scene_key: str, task_keys: list[str]) -> Any:
    """What the run flies scene ``scene_key`` at (its task sets among ``task_keys``), for
    ingestion's warnings: only those views and regions, not the paper's 15 m views and
    150 m tasks at 300 m."""
    from geonav.tiles.ingest import CoverageNeeds

    views: list[tuple[float, int, float]] = []
    tasks: list[tuple[float, float, float]] = []
    for key in task_keys:
        t = cfg.tasks[key]
        if t.scene != scene_key or t.path:
            continue
        alts = (t.alt_m,) if t.kind == "meta" else tuple(t.alts_m)
        views += [(float(a), t.obs_size_px, t.fov_deg) for a in alts]
        if t.kind == "meta":
            tasks.append((float(t.size_m or 150.0), float(t.margin_alt_m or t.alt_m),
                          t.fov_deg))
    return CoverageNeeds(tuple(views), tuple(tasks))


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


def make_taskset(spec: TaskSpec, scene_path: str,
                 progress: Callable[[str, float], None] | None = None):
    """The task set a :class:`TaskSpec` describes, on its scene (``progress``: callback
    (phase, fraction) of the sampler, its phases named after the task set)."""
    from geonav.camera import Camera
    from geonav.scene import Scene
    from geonav.tasks import sample_meta_tasks, whole_scene_tasks

    scene = Scene.open(scene_path)
    camera = Camera(spec.obs_size_px, spec.fov_deg)
    named = None if progress is None else \
        (lambda phase, f: progress(f"{phase} of {spec.name}", f))  # type: ignore[misc]
    if spec.kind == "meta":
        return sample_meta_tasks(scene, spec.count, size_m=spec.size_m or 150.0,
                                 alt_m=spec.alt_m, step_m=spec.step_m, max_steps=spec.max_steps,
                                 seed=spec.seed, camera=camera, margin_alt_m=spec.margin_alt_m,
                                 max_overlap=spec.max_overlap,
                                 max_random_walk=spec.max_random_walk,
                                 max_blind=spec.max_blind, progress=named)
    return whole_scene_tasks(scene, spec.alts_m, step_m=spec.step_m, max_steps=spec.max_steps,
                             seed=spec.seed, size_m=spec.size_m, camera=camera,
                             max_random_walk=spec.max_random_walk, max_blind=spec.max_blind,
                             progress=named)
