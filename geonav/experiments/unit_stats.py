"""What one unit of an experiment run reached: its metrics, evaluations and convergence.

:func:`unit_stats` reads a unit's ``result.json``, ``metrics.csv`` and ``eval.csv``
(:func:`read_success`, :func:`read_evals`, :func:`read_eval_column`), or the files of
one still running (:func:`in_progress_result`), and gives its e* by both convergence
rules (:mod:`geonav.convergence`), wall time and final evaluation: the figures
:mod:`geonav.experiments.report` puts into its tables.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from geonav.convergence import (
    ConvergenceCriterion,
    area_under_curve,
    episodes_to_convergence,
    eval_convergence,
)
from geonav.errors import ReportError
from geonav.experiments.units import RESULT, Unit, read_result, unit_dir


def read_success(metrics_csv: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(success, elapsed_s, length, shortest_path) per episode in completion order. A
    last row cut short (a run still writing, or killed mid-line) is left out.

    Raises:
        ReportError: a row that cannot be read is followed by others (a corrupt file, not
            a cut last row): the curve would silently stop there.
    """
    succ: list[bool] = []
    wall: list[float] = []
    length: list[float] = []
    short: list[float] = []
    bad: int | None = None
    with open(metrics_csv, newline="") as f:
        for line, row in enumerate(csv.DictReader(f), start=2):
            if bad is not None:
                raise ReportError(f"{metrics_csv}: line {bad} cannot be read (success, "
                                  "elapsed_s, length, shortest_path) but is not the last row; "
                                  "the file is corrupt: repair or remove that line, or rerun "
                                  "the unit (delete its folder)")
            try:
                values = (float(row["success"]) > 0.5, float(row.get("elapsed_s") or "nan"),
                          float(row.get("length") or "nan"),
                          float(row.get("shortest_path") or "nan"))
            except (TypeError, ValueError):
                bad = line
                continue
            succ.append(values[0])
            wall.append(values[1])
            length.append(values[2])
            short.append(values[3])
    return np.array(succ, bool), np.array(wall), np.array(length), np.array(short)


def read_evals(eval_csv: Path) -> tuple[np.ndarray, np.ndarray]:
    """(training episode, greedy SR over all starts) of a run's periodic evaluations."""
    ep, sr = [], []
    if eval_csv.exists():
        with open(eval_csv, newline="") as f:
            for row in csv.DictReader(f):
                ep.append(int(float(row["episode"])))
                sr.append(float(row["greedy_sr"]))
    return np.array(ep, int), np.array(sr)


def read_eval_column(eval_csv: Path, column: str) -> np.ndarray:
    """One figure of a run's periodic evaluations, row by row as :func:`read_evals` reads
    them (e.g. ``ablated_sr``, the view-ablated greedy SR); NaN where a row lacks it (files
    written before the column existed, or an empty cell)."""
    out: list[float] = []
    if eval_csv.exists():
        with open(eval_csv, newline="") as f:
            for row in csv.DictReader(f):
                try:
                    out.append(float(row.get(column) or "nan"))
                except ValueError:
                    out.append(math.nan)
    return np.array(out, float)


def in_progress_result(out_dir: Path) -> dict[str, Any] | None:
    """A stand-in result for a unit that has started but not finished (no result.json):
    where its metrics and evaluations are being written and how many episodes came before
    them. For a curriculum unit only its last level counts (the one its e* is measured on);
    one still on an earlier level gives None, as does a unit with no metrics yet."""
    curriculum = out_dir / "curriculum.json"
    if curriculum.exists():
        state = json.loads(curriculum.read_text())
        levels = state.get("curriculum", {}).get("levels_m") or []
        done = state.get("stages") or []
        if not levels or len(done) != len(levels) - 1:
            return None
        found = sorted(out_dir.glob(f"stage_{len(done)}_*/metrics.csv"))
        if not found:
            return None
        metrics = found[0]
        before = sum(int(st.get("episodes", 0)) for st in done)
    else:
        metrics, before = out_dir / "metrics.csv", 0
    if not metrics.exists():
        return None
    return dict(metrics=str(metrics), evals=str(metrics.with_name("eval.csv")),
                episodes_before_metrics=before, in_progress=True)


def unit_stats(root: Path, unit: Unit, criterion: ConvergenceCriterion,
               partial: bool = False) -> dict[str, Any] | None:
    """Convergence, wall time and final evaluation of one finished unit; with ``partial``,
    also of one still running (see :func:`in_progress_result`): its e* is taken over the
    episodes it has so far, so a run that has not met the rule counts, censored, at the
    episode it has reached (a lower bound), and it has no final evaluation.

    Raises:
        ReportError: the unit finished but its files cannot be read (a result.json that is
            not JSON, a metrics file it names that is missing or corrupt).
    """
    out_dir = unit_dir(root, unit)
    result_path = out_dir / RESULT
    if result_path.exists():
        found = read_result(out_dir)
        if found is None:
            raise ReportError(f"{result_path} cannot be read (not JSON); rerun the unit "
                              "(delete its folder)")
        result = found
    elif partial and (stand_in := in_progress_result(out_dir)) is not None:
        result = stand_in
    else:
        return None
    metrics = Path(result.get("metrics") or out_dir / "metrics.csv")
    if not metrics.exists():
        raise ReportError(f"{result_path} names the metrics file {metrics}, which does not "
                          "exist: copy the whole run folder, or rerun the unit (delete its "
                          "folder)")
    success, wall, length, short = read_success(metrics)
    conv = episodes_to_convergence(success, criterion)
    wall_to = None
    if conv.episodes is not None and len(wall) >= conv.episodes:
        wall_to = float(wall[conv.episodes - 1])
    tail = slice(max(0, len(success) - criterion.window), None)
    ok = success[tail]
    ratio = float(np.nanmean(length[tail][ok] / np.maximum(short[tail][ok], 1))) if ok.any() \
        else math.nan
    eval_path = Path(result.get("evals") or metrics.with_name("eval.csv"))
    eval_ep, eval_sr = read_evals(eval_path)
    eval_conv = eval_convergence(eval_ep, eval_sr, int(len(success)), criterion.eval_threshold)
    return dict(
        seed=unit.seed, conv=conv, eval_conv=eval_conv, eval_episodes=eval_ep,
        eval_greedy_sr=eval_sr, eval_ablated_sr=read_eval_column(eval_path, "ablated_sr"),
        episodes=int(len(success)), wall_to_convergence_s=wall_to,
        wall_total_s=float(wall[-1]) if len(wall) else None,
        auc=area_under_curve(success, criterion.window),
        length_over_shortest=ratio,
        eval=result.get("eval", {}), success=success,
        trajectories=result.get("trajectories", []), result=result,
        in_progress=bool(result.get("in_progress")),
    )


def evaluated(stats: list[dict[str, Any]]) -> list[Any]:
    """The evaluation e* of the runs that have periodic evaluation rows."""
    return [s["eval_conv"] for s in stats if s["eval_conv"].evaluations > 0]
