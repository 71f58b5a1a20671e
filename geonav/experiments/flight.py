"""Fly an experiment's result through the MAVLink vehicle emulator (a dry run).

The last step of the main job: the policy of one stage (by default the first
method of the first comparison, e.g. the transferred meta-policy) flies its
task on its scene through the same bridge code that flies PX4 or ArduPilot,
against the in-process emulator. The flight record (``flight.jsonl``) and
track picture land in ``runs/NAME/flight/`` and a section is appended to
``report.md``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from geonav.errors import ConfigError
from geonav.experiments.config import ExperimentConfig
from geonav.experiments.runner import RESULT, Unit, read_result, unit_dir

log = logging.getLogger(__name__)


def fly_result(cfg: ExperimentConfig, root: Path, progress: Any = None) -> dict[str, Any]:
    """Dry-run flight of ``cfg.flight['stage']`` (seed ``cfg.flight['seed']``); returns a summary.

    ``[flight]`` keys: stage, seed, task_index, autopilot ("px4" | "ardupilot"),
    backend ("pymavlink" | "mavsdk"), start_seed, sample (sampled actions, default true).
    """
    from geonav.mavlink_bridge.flight import fly
    from geonav.scene import Scene
    from geonav.tasks import TaskSet, bind

    fl = dict(cfg.flight)
    stage = fl.get("stage") or (cfg.compare[0].methods[0] if cfg.compare else None)
    if stage not in cfg.stages:
        raise ConfigError(f"[flight] stage = {stage!r} is not a stage of {cfg.name}")
    seed = int(fl.get("seed", cfg.seeds[0]))
    result_path = unit_dir(root, Unit(stage, seed)) / RESULT
    if not result_path.exists():
        raise ConfigError(f"[flight]: stage {stage} seed {seed} has not finished "
                          f"({result_path} missing)")
    result = read_result(result_path.parent)
    if result is None:
        raise ConfigError(f"[flight]: {result_path} cannot be read (not JSON)")
    scene = Scene.open(result["scene"])
    ts = TaskSet.load(result["tasks"])
    task = ts.tasks[int(fl.get("task_index", 0))]
    tm = bind(task, scene, ts.camera)
    starts = tm.start_cells()
    rng = np.random.default_rng(int(fl.get("start_seed", 0)))
    start = starts[int(rng.integers(len(starts)))]
    out = root / "flight"
    from geonav.policy.inference import PolicyRunner

    # Sampled actions by default, as the evaluation protocol (ALGORITHMS.md (f)); a greedy
    # recurrent policy can lock into a loop. `sample = false` flies the argmax.
    sample = bool(fl.get("sample", True))
    policy = PolicyRunner.from_checkpoint(result["checkpoint"], greedy=not sample,
                                          seed=int(fl.get("start_seed", 0)))
    # The task gives region, step, altitude, target, step budget and obstacle model; SIGINT,
    # SIGTERM and SIGHUP during the flight land the emulated vehicle and write the record.
    flight = fly(
        policy, scene, task=task, start_cell=start,
        dry_run=True, autopilot=fl.get("autopilot", "px4"),
        backend=fl.get("backend", "pymavlink"), out_dir=out, progress=progress,
        max_alt_m=max(120.0, task.alt_m + 20.0),
    )
    summary = dict(stage=stage, seed=seed, task=task.name, alt_m=task.alt_m,
                   actions="sampled" if sample else "greedy",
                   start_cell=list(start), target_cell=list(task.target_cell),
                   shortest_path=int(tm.dist_to_target[start]), success=flight.success,
                   outcome=flight.outcome, exit_code=flight.exit_code,
                   reason=flight.reason, steps=flight.steps,
                   final_cell=None if flight.final_cell is None else list(flight.final_cell),
                   end_action=flight.end_action, end_ok=flight.end_ok,
                   disarmed=flight.disarmed,
                   record=str(flight.record_path),
                   track_png=None if flight.png_path is None else str(flight.png_path),
                   latency_ms_p50=float(np.median(flight.latencies_ms))
                   if flight.latencies_ms else None)
    out = Path(flight.record_path).parent  # flight-2, ... when an earlier record is there
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    report = root / "report.md"
    if report.exists():
        text = report.read_text().split("\n## Flight (MAVLink emulator)")[0].rstrip() + "\n"
        rel = Path(summary["track_png"]).relative_to(root) if summary["track_png"] else None
        text += (
            "\n## Flight (MAVLink emulator)\n\n"
            f"The final `{stage}` policy (seed {seed}, {summary['actions']} actions) flew task "
            f"`{task.name}` at "
            f"{task.alt_m:g} m through the MAVLink bridge against the "
            f"{fl.get('autopilot', 'px4')} emulator ({fl.get('backend', 'pymavlink')} backend), "
            f"from cell {tuple(start)} to {task.target_cell} (shortest path "
            f"{summary['shortest_path']} steps): "
            f"{'reached' if flight.success else 'not reached'} after {flight.steps} steps "
            f"({flight.reason}); ended with {flight.end_action}, "
            f"{'disarmed' if flight.disarmed else 'NOT disarmed'}. Record: "
            f"`{out.name}/{Path(summary['record']).name}`.\n"
            + (f"\n![flight track]({rel})\n" if rel else ""))
        report.write_text(text)
    if flight.outcome == "interrupted" and flight.signal_name:
        # The vehicle has landed and the record is written; now stop the experiment too.
        import signal

        from geonav.mavlink_bridge.flight import FlightInterrupted

        raise FlightInterrupted(int(signal.Signals[flight.signal_name]))
    return summary
