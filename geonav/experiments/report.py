"""summary.json and report.md of an experiment: convergence tables, curves, trajectories.

This module owns the report's text and summary: per comparison a table of both
convergence rules' e* over seeds, final evaluations, ratios and verdicts, and the
sections of the stages the methods start from. A unit's figures come from
:mod:`geonav.experiments.unit_stats`, the pictures from :mod:`geonav.experiments.plots`.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from geonav.convergence import (
    ConvergenceCriterion,
    ConvergenceResult,
    EvalConvergence,
    summarize,
)
from geonav.errors import MissingExtra, ReportError
from geonav.experiments.config import CompareSpec, ExperimentConfig
from geonav.experiments.plots import plot_curves, plot_trajectories
from geonav.experiments.unit_stats import (
    evaluated,
    in_progress_result,
    read_eval_column,
    read_evals,
    read_success,
    unit_stats,
)
from geonav.experiments.units import RESULT, Unit, read_result, unit_dir

#: Names that moved to :mod:`~geonav.experiments.unit_stats`, still importable from here.
__all__ = ["evaluated", "in_progress_result", "read_eval_column", "read_evals",
           "read_success", "unit_stats", "verdict", "write_report"]

log = logging.getLogger(__name__)


def verdict(a: str, ra: list[ConvergenceResult | EvalConvergence], b: str,
            rb: list[ConvergenceResult | EvalConvergence]) -> str:
    """"effect shown" only when the seed ranges of e* (censored runs at their budget, a
    lower bound) do not overlap; otherwise "no effect shown at this budget"."""
    if not ra or not rb:
        return "no effect shown (runs missing)"
    va, vb = [r.value() for r in ra], [r.value() for r in rb]
    if all(r.censored for r in ra) and all(r.censored for r in rb):
        return "no effect shown at this budget (neither converged)"
    if max(vb) < min(va) and not all(r.censored for r in rb):
        return (f"effect shown: {b} converges in fewer episodes than {a} (seed ranges "
                f"{min(vb):.0f}-{max(vb):.0f} vs {min(va):.0f}-{max(va):.0f}"
                f"{'+' if any(r.censored for r in ra) else ''} do not overlap)")
    if max(va) < min(vb) and not all(r.censored for r in ra):
        return (f"effect shown: {a} converges in fewer episodes than {b} (seed ranges "
                f"{min(va):.0f}-{max(va):.0f} vs {min(vb):.0f}-{max(vb):.0f}"
                f"{'+' if any(r.censored for r in rb) else ''} do not overlap)")
    return (f"no effect shown at this budget (seed ranges {min(va):.0f}-{max(va):.0f} and "
            f"{min(vb):.0f}-{max(vb):.0f} overlap)")


def _stats(root: Path, unit: Unit, criterion: ConvergenceCriterion, partial: bool,
           unreadable: dict[str, str]) -> dict[str, Any] | None:
    """:func:`unit_stats`, with a unit whose files cannot be read recorded in
    ``unreadable`` (key -> why) and left out, so one bad unit does not stop the report."""
    if unit.key in unreadable:
        return None
    try:
        return unit_stats(root, unit, criterion, partial)
    except ReportError as err:
        log.warning("unit %s left out of the report: %s", unit.key, err)
        unreadable[unit.key] = str(err)
        return None


def _seed_stats(results: list[Any]) -> dict[str, Any] | None:
    """IQM and bootstrap CIs of e* over seeds (geonav.experiments.stats; None without the
    ``stats`` extra or runs)."""
    if not results:
        return None
    from geonav.experiments.stats import seed_summary

    try:
        return seed_summary([r.value() for r in results], [r.censored for r in results])
    except MissingExtra:
        return None


def _fmt_iqm(st: dict[str, Any] | None) -> str:
    if not st or st.get("iqm") is None:
        return ""
    lo, hi = st["iqm_ci"]
    plus = "+" if st.get("iqm_censored") else ""
    return f"; IQM {st['iqm']:.0f}{plus} (95% CI {lo:.0f}-{hi:.0f})"


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
                 failed: dict[Unit, str], partial: bool = False,
                 parts: list[str] | None = None) -> dict[str, Any]:
    """Write summary.json, report.md and the PNGs; returns the summary. With ``partial``
    (an interim report of a run still going), units that have started but not finished
    count at the episode they have reached, and the report says so. With ``parts`` (the
    run's ``--only``), only those parts' comparisons are written, not every other part
    whose stages happen to be among ``stage_keys`` (a part that reuses another's runs).

    A unit whose files cannot be read (see :func:`unit_stats`) is left out and listed
    under "Unreadable units" and in ``summary["unreadable"]``."""
    crit = cfg.convergence
    lines = [f"# Experiment `{cfg.name}`", "",
             f"Config: `{cfg.source}`; seeds {list(cfg.seeds)}. Two convergence rules "
             f"(ALGORITHMS.md (f)), identical for every method: **training SR** over the last "
             f"W = {crit.window} episodes reaches {crit.threshold:g} and stays >= {crit.hold:g} "
             f"for the next W (the paper's e*), and **greedy evaluation**: the first periodic "
             f"evaluation at which greedy SR over all start cells is >= "
             f"{crit.eval_threshold:g} and stays so at the next one. The config passed the "
             "noise check (a policy that is not improving meets neither rule). A verdict says "
             "\"effect shown\" only when the seed ranges of e* do not overlap. The "
             "**view-ablated** greedy SR is the same greedy evaluation with the current view "
             "replaced, at every step, by the view of a random other cell of the same task "
             "(target kept): a policy that navigates by the view falls toward the view-blind "
             "line (the best policy that knows the target but ignores the view); one that "
             "keeps its SR is not using the view.", ""]
    summary: dict[str, Any] = {"name": cfg.name, "convergence": vars(crit) if hasattr(
        crit, "__dict__") else {}, "comparisons": [], "failed": {u.key: m for u, m in
                                                                 failed.items()}}
    summary["convergence"] = dict(window=crit.window, threshold=crit.threshold, hold=crit.hold,
                                  eval_threshold=crit.eval_threshold)
    unreadable: dict[str, str] = {}
    summary["unreadable"] = unreadable
    stats_by_stage: dict[str, list[dict[str, Any]]] = {}
    for key in stage_keys:
        stats_by_stage[key] = [s for seed in cfg.seeds
                               if (s := _stats(root, Unit(key, seed), crit, partial,
                                               unreadable)) is not None]
    running = [f"{key}/seed-{s['seed']} ({s['episodes']} episodes)"
               for key in stage_keys for s in stats_by_stage[key] if s["in_progress"]]
    summary["in_progress"] = running
    if running:
        lines += [f"**Interim report: {len(running)} unit(s) still running** "
                  f"({', '.join(running)}). A running unit counts at the episode it has "
                  "reached: if it has not met a rule yet, its e* is censored there (a lower "
                  "bound that can only grow), and it has no final evaluation yet (the final "
                  "columns are over finished units). Verdicts may change when they finish.",
                  ""]
    for comp in cfg.compare:
        if not all(m in stats_by_stage for m in comp.methods):
            continue
        if parts and (comp.part or comp.name) not in parts:
            continue
        lines += _comparison(cfg, comp, root, stats_by_stage, summary, scenes)
    if unreadable:
        lines += ["## Unreadable units", "", "Finished units whose files cannot be read; "
                  "they are left out of every figure above.", ""] + \
            [f"- `{k}`: {m}" for k, m in unreadable.items()] + [""]
    if failed:
        lines += ["## Failed units", ""] + [f"- `{u.key}`: {m}" for u, m in failed.items()] + [""]
    lines += ["## Stages", "", "| stage | mode | algo | tasks | budget | seeds done |",
              "|---|---|---|---|---|---|"]
    for key in stage_keys:
        st = cfg.stages[key]
        n_run = sum(s["in_progress"] for s in stats_by_stage[key])
        n_done = len(stats_by_stage[key]) - n_run
        n_bad = sum(f"{key}/seed-{seed}" in unreadable for seed in cfg.seeds)
        lines.append(f"| {key} | {st.mode} | {st.algo} | {st.tasks} | {st.episodes} | "
                     f"{n_done}/{len(cfg.seeds)}"
                     f"{f' (+{n_run} running)' if n_run else ''}"
                     f"{f' ({n_bad} unreadable)' if n_bad else ''} |")
    (root / "report.md").write_text("\n".join(lines) + "\n")
    (root / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    return summary


def _json_default(v: Any) -> Any:
    if isinstance(v, (ConvergenceResult, EvalConvergence)):
        return dict(episodes=v.episodes, budget=v.budget, censored=v.censored)
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    raise TypeError(type(v))


def _ratio_text(a: str, b: str, med: dict[str, float], cens: dict[str, bool],
                comp: CompareSpec, rule: str,
                all_cens: dict[str, bool] | None = None) -> tuple[str, float | None]:
    if a not in med or b not in med:
        return f"Ratio {b} / {a} ({rule}): n/a.", None
    ours = med[b] / med[a] if med[a] else math.nan
    if cens[a] and cens[b]:
        if all_cens is None or (all_cens.get(a, True) and all_cens.get(b, True)):
            text = f"Ratio {b} / {a} ({rule}): **n/a**, neither converged within its budget"
        else:  # some runs met the rule, but fewer than half of each method's
            text = (f"Ratio {b} / {a} ({rule}): **n/a**, both medians censored (most runs "
                    "never met the rule within their budget)")
        value = None
    elif cens[a]:
        text, value = f"Ratio {b} / {a} ({rule}): **<= {ours:.2f}** ({a} censored)", ours
    elif cens[b]:
        text, value = f"Ratio {b} / {a} ({rule}): **>= {ours:.2f}** ({b} censored)", ours
    else:
        text, value = f"Ratio {b} / {a} ({rule}): **{ours:.2f}**", ours
    if a in comp.paper and b in comp.paper:
        text += (f"; the paper's: {comp.paper[b] / comp.paper[a]:.2f} "
                 f"({comp.paper[b]:g} vs {comp.paper[a]:g} episodes)")
    return text + ".", value


def _f(v: float | None, spec: str = ".2f") -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def _comparison(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
                stats_by_stage: dict[str, list[dict[str, Any]]], summary: dict[str, Any],
                scenes: dict[str, str]) -> list[str]:
    crit = cfg.convergence
    lines = [f"## {comp.name}", ""]
    record: dict[str, Any] = {"name": comp.name, "claim": comp.claim or comp.name,
                              "part": comp.part or comp.name,
                              "order": list(comp.methods), "paper": dict(comp.paper),
                              "methods": {}}
    chance: dict[str, Any] = next((s["eval"] for m in comp.methods for s in stats_by_stage[m]
                                   if "random_walk_sr" in s["eval"]), {})
    if chance:
        lines += [f"Chance on this task (exact, DP over the lattice): a uniform random walk "
                  f"succeeds **{chance['random_walk_sr']:.3f}** of the time from the start "
                  f"cells, the best view-blind action bias (knows the target, ignores the view) "
                  f"{chance.get('blind_sr', math.nan):.3f}; mean shortest path "
                  f"{chance.get('mean_shortest_path', math.nan):.1f} steps.",
                  ""]
        record["random_walk_sr"] = chance["random_walk_sr"]
        record["blind_sr"] = chance.get("blind_sr")
    lines += [
        f"| method | e* training SR (W = {crit.window}, {crit.threshold:g} / {crit.hold:g}) | "
        f"e* greedy eval (>= {crit.eval_threshold:g} twice) | censored (train / eval) | "
        "final greedy SR / SPL | final sampled SR / SPL | final view-ablated greedy SR | "
        "zero-shot greedy SR | length / shortest (greedy) | wall time to e* (train) |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    med: dict[str, dict[str, float]] = {"train": {}, "eval": {}}
    cens: dict[str, dict[str, bool]] = {"train": {}, "eval": {}}
    all_cens: dict[str, dict[str, bool]] = {"train": {}, "eval": {}}
    for m in comp.methods:
        row, rec = _method_row(cfg, comp, root, m, stats_by_stage[m])
        lines.append(row)
        record["methods"][m] = rec
        for rule, c in (("train", rec["convergence_incl_parents"] or rec["convergence"]),
                        ("eval", rec["eval_convergence_incl_parents"]
                         or rec["eval_convergence"])):
            if c["median"] is not None:
                med[rule][m] = c["median"]
                cens[rule][m] = bool(c["median_censored"])
                all_cens[rule][m] = c["censored"] == c["n"]
    lines += ["", "median [min-max] over seeds; IQM: interquartile mean with a 95 % "
              "stratified-bootstrap interval (rliable). `+`: a lower bound (censored runs, "
              "which never met the rule within their budget, count at their budget).", ""]
    record.update(_compute(cfg, comp, root, stats_by_stage, summary["unreadable"]))
    if len(comp.methods) >= 2:
        lines += _ratios_and_verdicts(cfg, comp, root, stats_by_stage, med, cens, all_cens,
                                      record)
    png = plot_curves(cfg, comp, root, stats_by_stage, chance)
    lines += [f"![learning curves]({png.name})", ""]
    traj = plot_trajectories(cfg, comp, root, stats_by_stage, scenes)
    if traj is not None:
        lines += [f"![trajectories]({traj.name})", ""]
    lines += _parent_sections(cfg, comp, root, summary, record)
    summary["comparisons"].append(record)
    return lines


def _method_row(cfg: ExperimentConfig, comp: CompareSpec, root: Path, m: str,
                stats: list[dict[str, Any]]) -> tuple[str, dict[str, Any]]:
    """One method's row of a comparison table and its record in summary.json."""
    conv = summarize([s["conv"] for s in stats])
    # runs without evaluation rows (eval_every = 0, no eval.csv) have no evaluation e*
    econv = summarize(evaluated(stats))
    # count_parents: e* by both rules (and so the ratios and verdicts) counts every
    # episode of the stages the method started from (meta-training, earlier levels)
    conv_total = summarize([_with_parents(cfg, root, m, s, s["conv"]) for s in stats]) \
        if comp.count_parents else None
    econv_total = summarize([_with_parents(cfg, root, m, s, s["eval_conv"])
                             for s in stats if s["eval_conv"].evaluations > 0]) \
        if comp.count_parents else None
    wall = _median([s["wall_to_convergence_s"] for s in stats])
    ev = [s["eval"] for s in stats]
    g_sr, g_spl = _median([e.get("greedy_sr") for e in ev]), \
        _median([e.get("greedy_spl") for e in ev])
    s_sr, s_spl = _median([e.get("sampled_sr", e.get("success_rate")) for e in ev]), \
        _median([e.get("sampled_spl", e.get("spl")) for e in ev])
    a_sr = _median([e.get("ablated_sr") for e in ev])
    zs = [e["zero_shot"]["greedy_sr"] for e in ev if e.get("zero_shot")]
    zs_med = _median(zs)
    zs_abl = _median([e["zero_shot"].get("ablated_sr") for e in ev if e.get("zero_shot")])
    ratio = _median([e.get("greedy_length_ratio") for e in ev])
    st_train = _seed_stats([s["conv"] for s in stats])
    st_eval = _seed_stats(evaluated(stats))
    cell = _fmt_conv(conv) + _fmt_iqm(st_train)
    if conv_total is not None:
        cell += f" (incl. earlier stages: {_fmt_conv(conv_total)})"
    n_run = sum(s["in_progress"] for s in stats)
    if n_run:
        cell += f" ({n_run} of {len(stats)} still running)"
    ecell = _fmt_conv(econv) + _fmt_iqm(st_eval)
    if econv_total is not None:
        ecell += f" (incl. earlier stages: {_fmt_conv(econv_total)})"
    row = (
        f"| {m} | {cell} | {ecell} | "
        f"{conv['censored']}/{conv['n']} / "
        f"{econv['censored']}/{econv['n']} | {_f(g_sr)} / {_f(g_spl)} | "
        f"{_f(s_sr)} / {_f(s_spl)} | {_f(a_sr)} | "
        f"{_f(zs_med) + (f' [{min(zs):.2f}-{max(zs):.2f}]' if zs else '')}"
        f"{f' (view-ablated {zs_abl:.2f})' if zs_abl is not None else ''} | "
        f"{_f(ratio)} | {'n/a' if wall is None else f'{wall:.1f} s'} |")
    rec = dict(
        convergence=conv, eval_convergence=econv, convergence_incl_parents=conv_total,
        eval_convergence_incl_parents=econv_total,
        convergence_stats=st_train, eval_convergence_stats=st_eval,
        wall_to_convergence_s=wall, final_greedy_sr=g_sr, final_greedy_spl=g_spl,
        final_sampled_sr=s_sr, final_sampled_spl=s_spl, final_ablated_sr=a_sr,
        zero_shot_greedy_sr=zs_med, zero_shot_ablated_sr=zs_abl,
        greedy_length_over_shortest=ratio,
        auc=_median([s["auc"] for s in stats]),
        in_progress=sum(s["in_progress"] for s in stats),
        runs=[dict(seed=s["seed"], conv=s["conv"], eval_conv=s["eval_conv"],
                   episodes=s["episodes"], eval=s["eval"], in_progress=s["in_progress"],
                   wall_total_s=s["wall_total_s"]) for s in stats])
    return row, rec


def _ratios_and_verdicts(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
                         stats_by_stage: dict[str, list[dict[str, Any]]],
                         med: dict[str, dict[str, float]], cens: dict[str, dict[str, bool]],
                         all_cens: dict[str, dict[str, bool]],
                         record: dict[str, Any]) -> list[str]:
    """The ratio and verdict lines of a comparison's first two methods, by both rules
    (stored into ``record``)."""
    lines: list[str] = []
    a, b = comp.methods[:2]
    record["ratio"], record["eval_ratio"] = None, None
    record["paper_ratio"] = comp.paper[b] / comp.paper[a] \
        if a in comp.paper and b in comp.paper and comp.paper[a] else None
    for rule, label in (("train", "training-SR e*"), ("eval", "greedy-evaluation e*")):
        text, value = _ratio_text(a, b, med[rule], cens[rule], comp, label,
                                  all_cens[rule])
        lines += [text, ""]
        record["ratio" if rule == "train" else "eval_ratio"] = value
    for rule, key, label in (("train", "conv", "training-SR rule"),
                             ("eval", "eval_conv", "greedy-evaluation rule")):
        def pick(method: str, key: str = key) -> list[Any]:
            runs = [s for s in stats_by_stage[method]
                    if key == "conv" or s["eval_conv"].evaluations > 0]
            if comp.count_parents:
                return [_with_parents(cfg, root, method, s, s[key]) for s in runs]
            return [s[key] for s in runs]

        v = verdict(a, pick(a), b, pick(b))
        record["verdict" if rule == "train" else "eval_verdict"] = v
        lines += [f"**Verdict ({label}): {v}.**", ""]
    return lines


def _compute(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
             stats_by_stage: dict[str, list[dict[str, Any]]],
             unreadable: dict[str, str]) -> dict[str, Any]:
    """Compute a comparison used: the training wall seconds of every finished unit of its
    methods and of the stages they start from, summed (``compute_s``), and their count."""
    keys: list[str] = []
    for m in comp.methods:
        k: str | None = m
        while k is not None and k not in keys:
            keys.append(k)
            k = cfg.stages[k].init
    total, units = 0.0, 0
    for k in keys:
        stats = stats_by_stage.get(k)
        if stats is None:
            stats = [s for seed in cfg.seeds
                     if (s := _stats(root, Unit(k, seed), cfg.convergence, False, unreadable))
                     is not None]
        for s in stats:
            if s["wall_total_s"] is not None and not math.isnan(s["wall_total_s"]):
                total += float(s["wall_total_s"])
                units += 1
    return {"compute_s": round(total, 3), "compute_units": units}


def _parent_sections(cfg: ExperimentConfig, comp: CompareSpec, root: Path,
                     summary: dict[str, Any], record: dict[str, Any]) -> list[str]:
    """The stages the compared methods start from (meta-training): their own curves, so a
    meta-policy that learned nothing is visible at a glance."""
    lines: list[str] = []
    parents = []
    for m in comp.methods:
        p = cfg.stages[m].init
        while p is not None:
            if p not in parents:
                parents.append(p)
            p = cfg.stages[p].init
    for p in parents:
        stats = [s for seed in cfg.seeds
                 if (s := _stats(root, Unit(p, seed), cfg.convergence, False,
                                 summary["unreadable"])) is not None]
        if not stats:
            continue
        st = cfg.stages[p]
        ev = [s["eval"] for s in stats]
        chance: dict[str, Any] = next((e for e in ev if "random_walk_sr" in e), {})
        children = [m for m in comp.methods if cfg.stages[m].init == p]
        zs = [r["eval"]["zero_shot"]["greedy_sr"] for m in children
              for r in record["methods"][m]["runs"] if r["eval"].get("zero_shot")]
        zs_abl = _median([r["eval"]["zero_shot"].get("ablated_sr") for m in children
                          for r in record["methods"][m]["runs"] if r["eval"].get("zero_shot")])
        own_abl = _median([e.get("ablated_sr") for e in ev])
        levels = {cfg.stages[m].init_alt_m for m in children}
        which = (f"{levels.pop():g} m level's policy"
                 if len(levels) == 1 and None not in levels else "final policy")
        lines += [f"### Starting stage `{p}` ({st.mode}, {st.algo}, tasks `{st.tasks}`)", "",
                  f"Final greedy SR over its own tasks' starts: "
                  f"{_f(_median([e.get('greedy_sr') for e in ev]))} (sampled "
                  f"{_f(_median([e.get('sampled_sr') for e in ev]))}; view-ablated "
                  f"{_f(own_abl)}; random walk "
                  f"{_f(chance.get('random_walk_sr'), '.3f')}, best view-blind "
                  f"{_f(chance.get('blind_sr'), '.3f')}). Zero-shot greedy SR of its "
                  f"{which} on the compared task: "
                  f"{_f(_median(zs))}" + (f" [{min(zs):.2f}-{max(zs):.2f}]" if zs else "") +
                  (f", view-ablated {zs_abl:.2f}" if zs_abl is not None else "") +
                  (f" (that task's random walk: {record['random_walk_sr']:.3f}"
                   + (f", best view-blind: {record['blind_sr']:.3f}"
                      if record.get("blind_sr") is not None else "") + ")"
                   if "random_walk_sr" in record else "") + ".", ""]
        fake = CompareSpec(name=f"{comp.name} - stage {p}", methods=(p,))
        png = plot_curves(cfg, fake, root, {p: stats}, chance)
        lines += [f"![{p} curves]({png.name})", ""]
        summary.setdefault("stages", {})[p] = dict(
            final_greedy_sr=_median([e.get("greedy_sr") for e in ev]),
            final_sampled_sr=_median([e.get("sampled_sr") for e in ev]),
            final_ablated_sr=own_abl,
            random_walk_sr=chance.get("random_walk_sr"), zero_shot_greedy_sr=_median(zs),
            zero_shot_ablated_sr=zs_abl)
    return lines


def _with_parents(cfg: ExperimentConfig, root: Path, stage: str, s: dict[str, Any],
                  conv: ConvergenceResult | EvalConvergence
                  ) -> ConvergenceResult | EvalConvergence:
    """``conv`` (an e* of the final stage by either rule) plus all episodes of the stages
    it started from (and of earlier curriculum levels)."""
    extra = int(s["result"].get("episodes_before_metrics", 0))
    parent = cfg.stages[stage].init
    while parent is not None:
        r = read_result(unit_dir(root, Unit(parent, s["seed"])))
        if r is None:
            raise ReportError(f"count_parents: {unit_dir(root, Unit(parent, s['seed']))} has "
                              f"no readable {RESULT}; its episodes cannot be counted")
        extra += int(r.get("episodes", 0))
        parent = cfg.stages[parent].init
    return replace(conv, episodes=None if conv.episodes is None else conv.episodes + extra,
                   budget=conv.budget + extra)


