"""summary.json and report.md of an experiment: convergence tables, curves, trajectories."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from geonav.experiments.config import CompareSpec, ExperimentConfig
from geonav.experiments.convergence import (
    ConvergenceCriterion,
    ConvergenceResult,
    area_under_curve,
    episodes_to_convergence,
    moving_success_rate,
    summarize,
)
from geonav.experiments.runner import RESULT, Unit, unit_dir


def read_success(metrics_csv: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(success, elapsed_s, length, shortest_path) per episode in completion order."""
    succ, wall, length, short = [], [], [], []
    with open(metrics_csv, newline="") as f:
        for row in csv.DictReader(f):
            succ.append(float(row["success"]) > 0.5)
            wall.append(float(row.get("elapsed_s") or "nan"))
            length.append(float(row.get("length") or "nan"))
            short.append(float(row.get("shortest_path") or "nan"))
    return np.array(succ, bool), np.array(wall), np.array(length), np.array(short)


def unit_stats(root: Path, unit: Unit, criterion: ConvergenceCriterion) -> dict[str, Any] | None:
    """Convergence, wall time and final evaluation of one finished unit."""
    out_dir = unit_dir(root, unit)
    result_path = out_dir / RESULT
    if not result_path.exists():
        return None
    result = json.loads(result_path.read_text())
    metrics = Path(result.get("metrics", out_dir / "metrics.csv"))
    if not metrics.exists():
        return None
    success, wall, length, short = read_success(metrics)
    conv = episodes_to_convergence(success, criterion)
    wall_to = None
    if conv.episodes is not None and len(wall) >= conv.episodes:
        wall_to = float(wall[conv.episodes - 1])
    tail = slice(max(0, len(success) - criterion.window), None)
    ok = success[tail]
    ratio = float(np.nanmean(length[tail][ok] / np.maximum(short[tail][ok], 1))) if ok.any() \
        else math.nan
    return dict(
        seed=unit.seed, conv=conv, episodes=int(len(success)), wall_to_convergence_s=wall_to,
        wall_total_s=float(wall[-1]) if len(wall) else None,
        auc=area_under_curve(success, criterion.window),
        length_over_shortest=ratio,
        eval=result.get("eval", {}), success=success,
        trajectories=result.get("trajectories", []), result=result,
    )


def _fmt_conv(s: dict[str, Any]) -> str:
    if s["n"] == 0:
        return "n/a"
    med = f"{s['median']:.0f}" + ("+" if s["median_censored"] else "")
    return f"{med} [{s['min']:.0f}-{s['max']:.0f}]"


def _median(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.median(vals)) if vals else None


def write_report(cfg: ExperimentConfig, root: Path, stage_keys: list[str],
                 scenes: dict[str, str], tasks: dict[str, str],
                 failed: dict[Unit, str]) -> dict[str, Any]:
    """Write summary.json, report.md and the PNGs; returns the summary."""
    crit = cfg.convergence
    lines = [f"# Experiment `{cfg.name}`", "",
             f"Config: `{cfg.source}`; seeds {list(cfg.seeds)}; convergence: SR over the last "
             f"W = {crit.window} episodes reaches {crit.threshold} and stays >= {crit.hold} for "
             f"the next W (ALGORITHMS.md (f)). `+` marks a censored median (at least half the "
             "runs never converged within their budget; their budget counts as a lower bound).",
             ""]
    summary: dict[str, Any] = {"name": cfg.name, "convergence": vars(crit) if hasattr(
        crit, "__dict__") else {}, "comparisons": [], "failed": {u.key: m for u, m in
                                                                 failed.items()}}
    summary["convergence"] = dict(window=crit.window, threshold=crit.threshold, hold=crit.hold)
    stats_by_stage: dict[str, list[dict[str, Any]]] = {}
    for key in stage_keys:
        stats_by_stage[key] = [s for seed in cfg.seeds
                               if (s := unit_stats(root, Unit(key, seed), crit)) is not None]
    for comp in cfg.compare:
        if not all(m in stats_by_stage for m in comp.methods):
            continue
        lines += _comparison(cfg, comp, root, stats_by_stage, summary, scenes)
    if failed:
        lines += ["## Failed units", ""] + [f"- `{u.key}`: {m}" for u, m in failed.items()] + [""]
    lines += ["## Stages", "", "| stage | mode | algo | tasks | budget | seeds done |",
              "|---|---|---|---|---|---|"]
    for key in stage_keys:
        st = cfg.stages[key]
        lines.append(f"| {key} | {st.mode} | {st.algo} | {st.tasks} | {st.episodes} | "
                     f"{len(stats_by_stage[key])}/{len(cfg.seeds)} |")
    (root / "report.md").write_text("\n".join(lines) + "\n")
    (root / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    return summary


def _json_default(v: Any) -> Any:
    if isinstance(v, ConvergenceResult):
        return dict(episodes=v.episodes, budget=v.budget, censored=v.censored)
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    raise TypeError(type(v))


def _comparison(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
                stats_by_stage: dict[str, list[dict[str, Any]]], summary: dict[str, Any],
                scenes: dict[str, str]) -> list[str]:
    lines = [f"## {comp.name}", "",
             "| method | episodes to convergence, median [min-max] | censored | "
             "wall time to convergence (median) | final success | final SPL | "
             "length / shortest (last W) | SR AUC |", "|---|---|---|---|---|---|---|---|"]
    record: dict[str, Any] = {"name": comp.name, "methods": {}}
    medians: dict[str, float] = {}
    censored: dict[str, bool] = {}
    for m in comp.methods:
        stats = stats_by_stage[m]
        conv = summarize([s["conv"] for s in stats])
        if comp.count_parents:
            conv_total = summarize([_with_parents(cfg, root, m, s) for s in stats])
        else:
            conv_total = None
        wall = _median([s["wall_to_convergence_s"] for s in stats])
        sr = _median([s["eval"].get("success_rate") for s in stats])
        spl = _median([s["eval"].get("spl") for s in stats])
        ratio = _median([s["length_over_shortest"] for s in stats])
        auc = _median([s["auc"] for s in stats])
        cell = _fmt_conv(conv)
        if conv_total is not None:
            cell += f" (incl. earlier stages: {_fmt_conv(conv_total)})"
        lines.append(
            f"| {m} | {cell} | {conv['censored']}/{conv['n']} | "
            f"{'n/a' if wall is None else f'{wall:.1f} s'} | "
            f"{'n/a' if sr is None else f'{sr:.2f}'} | {'n/a' if spl is None else f'{spl:.2f}'} | "
            f"{'n/a' if ratio is None else f'{ratio:.2f}'} | "
            f"{'n/a' if auc is None else f'{auc:.2f}'} |")
        if conv["median"] is not None:
            medians[m] = (conv_total or conv)["median"]
            censored[m] = bool((conv_total or conv)["median_censored"])
        record["methods"][m] = dict(convergence=conv, convergence_incl_parents=conv_total,
                                    wall_to_convergence_s=wall, final_success=sr, final_spl=spl,
                                    length_over_shortest=ratio, auc=auc,
                                    runs=[dict(seed=s["seed"], conv=s["conv"],
                                               episodes=s["episodes"], eval=s["eval"],
                                               wall_total_s=s["wall_total_s"]) for s in stats])
    lines.append("")
    if len(comp.methods) >= 2 and all(m in medians for m in comp.methods[:2]):
        a, b = comp.methods[:2]
        ours = medians[b] / medians[a] if medians[a] else math.nan
        if censored[a] and censored[b]:
            text = (f"Ratio {b} / {a}: **n/a**, neither converged within its budget "
                    "(compare the curves and the SR AUC)")
        elif censored[a]:
            text = f"Ratio {b} / {a} (median episodes): **<= {ours:.2f}** ({a} censored)"
        elif censored[b]:
            text = f"Ratio {b} / {a} (median episodes): **>= {ours:.2f}** ({b} censored)"
        else:
            text = f"Ratio {b} / {a} (median episodes): **{ours:.2f}**"
        if a in comp.paper and b in comp.paper:
            text += f"; the paper's: {comp.paper[b] / comp.paper[a]:.2f} " \
                    f"({comp.paper[b]:g} vs {comp.paper[a]:g} episodes)"
        lines += [text + ".", ""]
        record["ratio"] = None if censored[a] and censored[b] else ours
    png = _plot_curves(cfg, comp, root, stats_by_stage)
    lines += [f"![learning curves]({png.name})", ""]
    traj = _plot_trajectories(cfg, comp, root, stats_by_stage, scenes)
    if traj is not None:
        lines += [f"![trajectories]({traj.name})", ""]
    summary["comparisons"].append(record)
    return lines


def _with_parents(cfg: ExperimentConfig, root: Path, stage: str, s: dict[str, Any]
                  ) -> ConvergenceResult:
    """e* of the final stage plus all episodes of the stages it started from."""
    extra = int(s["result"].get("episodes_before_metrics", 0))
    parent = cfg.stages[stage].init
    while parent is not None:
        r = json.loads((unit_dir(root, Unit(parent, s["seed"])) / RESULT).read_text())
        extra += int(r.get("episodes", 0))
        parent = cfg.stages[parent].init
    conv: ConvergenceResult = s["conv"]
    return ConvergenceResult(None if conv.episodes is None else conv.episodes + extra,
                             conv.budget + extra)


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in text.lower()).strip("-")


def _plot_curves(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
                 stats_by_stage: dict[str, list[dict[str, Any]]]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    w = cfg.convergence.window
    for m in comp.methods:
        curves = [moving_success_rate(s["success"], min(w, max(1, len(s["success"]))))
                  for s in stats_by_stage[m]]
        if not curves:
            continue
        n = max(len(c) for c in curves)
        padded = np.full((len(curves), n), np.nan)
        for i, c in enumerate(curves):
            padded[i, :len(c)] = c
        x = np.arange(1, n + 1)
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(padded, axis=0)
                lo, hi = np.nanmin(padded, axis=0), np.nanmax(padded, axis=0)
        (line,) = ax.plot(x, med, label=f"{m} (median of {len(curves)} seeds)")
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)
    ax.axhline(cfg.convergence.threshold, color="grey", ls="--", lw=0.8)
    ax.set_xlabel("training episodes")
    ax.set_ylabel(f"success rate (last {w} episodes)")
    ax.set_ylim(0, 1.02)
    ax.set_title(comp.name)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    out = root / f"curves-{_slug(comp.name)}.png"
    fig.savefig(out)
    plt.close(fig)
    return out


def _plot_trajectories(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
                       stats_by_stage: dict[str, list[dict[str, Any]]],
                       scenes: dict[str, str]) -> Path | None:
    from geonav.scene import Scene
    from geonav.tasks import TaskSet
    from geonav.viz import draw_scene

    tracks = []
    scene_key = None
    taskset = None
    for m in comp.methods:
        stats = stats_by_stage[m]
        if not stats or not stats[0]["trajectories"]:
            continue
        stage = cfg.stages[m]
        tspec = cfg.tasks[stage.tasks]
        scene_key = tspec.scene
        taskset = TaskSet.load(stats[0]["result"]["tasks"])
        for traj in stats[0]["trajectories"][:2]:
            task = taskset.tasks[int(traj["task_index"])]
            cells = [tuple(c) for c in traj["cells"]]
            tracks.append((task, cells, f"{m} seed {stats[0]['seed']}: "
                           f"{'reached' if traj['success'] else 'missed'} in "
                           f"{len(cells) - 1} steps"))
    if not tracks or scene_key is None or taskset is None:
        return None
    scene = Scene.open(scenes[scene_key])
    out = root / f"trajectories-{_slug(comp.name)}.png"
    used = {id(t[0]): t[0] for t in tracks}
    draw_scene(scene, out, tasks=list(used.values()), tracks=tracks, footprints_at=(),
               title=f"{comp.name}: greedy trajectories of the final policies")
    return out
