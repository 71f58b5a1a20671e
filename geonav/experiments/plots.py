"""The pictures of an experiment report: learning curves and greedy trajectories.

:func:`plot_curves` draws training SR and greedy-evaluation SR over episodes (median
and min-max band over seeds, chance lines); :func:`plot_trajectories` draws the final
policies' greedy paths on the scene (:func:`geonav.viz.draw_scene`). Both write a PNG
into the run folder and return its path; :mod:`geonav.experiments.report` links them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from geonav.convergence import moving_success_rate
from geonav.experiments.config import CompareSpec, ExperimentConfig


def slug(text: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in text.lower()).strip("-")


def _band(curves: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import warnings

    n = max(len(c) for c in curves)
    padded = np.full((len(curves), n), np.nan)
    for i, c in enumerate(curves):
        padded[i, :len(c)] = c
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return (np.nanmedian(padded, axis=0), np.nanmin(padded, axis=0),
                np.nanmax(padded, axis=0))


def plot_curves(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
                 stats_by_stage: dict[str, list[dict[str, Any]]],
                 chance: dict[str, Any] | None = None) -> Path:
    """Two panels: training SR over the last W episodes, and greedy SR over all starts at
    each periodic evaluation (with the view-ablated greedy SR dashed, where the rows have
    it); median and min-max band over seeds; chance lines drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4), dpi=110, sharey=True)
    n_max = max([len(s["success"]) for m in comp.methods for s in stats_by_stage[m]] or [1])
    w = max(1, min(cfg.convergence.window, n_max // 5 or 1))
    for m in comp.methods:
        stats = stats_by_stage[m]
        curves = [moving_success_rate(s["success"], min(w, max(1, len(s["success"]))))
                  for s in stats]
        if not curves:
            continue
        med, lo, hi = _band(curves)
        x = np.arange(1, len(med) + 1)
        (line,) = ax.plot(x, med, label=f"{m} (median of {len(curves)} seeds)")
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)
        ablated_label = True
        for i, s in enumerate(stats):
            if len(s["eval_episodes"]):
                ax2.plot(s["eval_episodes"], s["eval_greedy_sr"], marker=".", ms=4, lw=1,
                         color=line.get_color(), alpha=0.8,
                         label=f"{m}" if i == 0 else None)
            abl = np.asarray(s.get("eval_ablated_sr", ()), float)
            if len(abl) == len(s["eval_episodes"]) and np.isfinite(abl).any():
                ok = np.isfinite(abl)
                ax2.plot(np.asarray(s["eval_episodes"])[ok], abl[ok], ls="--", lw=1,
                         color=line.get_color(), alpha=0.8,
                         label=f"{m}, view-ablated" if ablated_label else None)
                ablated_label = False
    for a in (ax, ax2):
        if chance and "random_walk_sr" in chance:
            a.axhline(chance["random_walk_sr"], color="red", ls=":", lw=1,
                      label=f"random walk {chance['random_walk_sr']:.2f}")
        if chance and chance.get("blind_sr") is not None:
            a.axhline(chance["blind_sr"], color="orange", ls=":", lw=1,
                      label=f"best view-blind {chance['blind_sr']:.2f}")
        a.set_xlabel("training episodes")
        a.set_ylim(0, 1.02)
        a.legend(loc="lower right", fontsize=7)
    ax.axhline(cfg.convergence.threshold, color="grey", ls="--", lw=0.8)
    ax2.axhline(cfg.convergence.eval_threshold, color="grey", ls="--", lw=0.8)
    ax.set_ylabel("success rate")
    ax.set_title(f"training SR (sampled actions, last {w} episodes)", fontsize=9)
    ax2.set_title("greedy SR over all start cells (one line per seed; dashed: "
                  "view-ablated)", fontsize=9)
    fig.suptitle(comp.name, fontsize=10)
    fig.tight_layout()
    out = root / f"curves-{slug(comp.name)}.png"
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_trajectories(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
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
    out = root / f"trajectories-{slug(comp.name)}.png"
    used = {id(t[0]): t[0] for t in tracks}
    # Zoomed to the flown regions and at a modest resolution: a whole 2.5 km scene at
    # full size made 2.4 MB PNGs of which the tracks filled a corner.
    regions = np.array([t.region_m for t in used.values()], dtype=float)
    x0, y0 = regions[:, 0].min(), regions[:, 1].min()
    x1, y1 = regions[:, 2].max(), regions[:, 3].max()
    pad = 0.08 * max(x1 - x0, y1 - y0)
    draw_scene(scene, out, tasks=list(used.values()), tracks=tracks, footprints_at=(),
               bounds_m=(x0 - pad, y0 - pad, x1 + pad, y1 + pad), dpi=90,
               title=f"{comp.name}: greedy trajectories of the final policies")
    return out
