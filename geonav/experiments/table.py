"""README's results table, generated from ``docs/results/*/summary.json`` (issue 12, item 4).

One row per comparison of every experiment's summary (written by
:func:`geonav.experiments.report.write_report`): the claim (the comparison, linked to its
report), the paper's ratio, ours by each convergence rule with the seed ranges of e*, a
verdict and the compute used. The table lives in README between the two marker comments
:data:`START` and :data:`END`; :func:`update_readme` rewrites only that block (a second
run changes nothing) and with ``check=True`` only says whether it is out of date.

Ratios are e* of the second method over the first, in the comparison's order (the
config's ``methods``), each the median over seeds; with the paper's episodes for both
methods the paper's ratio is formed the same way. Verdicts, per rule, from the report's
(which says "effect shown" only when the seed ranges of e* do not overlap):
"reproduced" when an effect is shown in the paper's direction, "not reproduced" when one
is shown the other way, else "no effect shown at this budget"; the row's verdict is
"reproduced" when both rules reproduce, "not reproduced" when either contradicts the
paper, "reproduced by the ... rule only" when one does and the other shows nothing (without a
paper figure: "effect shown (X faster) by the ... rule only").
A "reproduced" direction whose ratio (by any rule; by the one rule that shows it, for
"... rule only") lies more than a factor :data:`SIZE_TOLERANCE` from the paper's reads
"direction reproduced, size not (...)".

Chance on the task: the column "chance: random walk / view-blind" gives the comparison's
``random_walk_sr`` (uniform random actions) and ``blind_sr`` (the best view-blind policy: it
knows the task's target but ignores the current view; per task the best stationary action
distribution, mean over tasks), "n/a" where the summary lacks them. With chance the larger
of the two, a convergence rule whose threshold (``threshold`` for the training-SR rule,
``eval_threshold`` for the greedy-evaluation rule, from the summary's ``convergence``) lies
below :func:`view_blind_floor`, chance plus half the gap to 1, can be met without using the
view, so its verdict cannot show navigation by the view: the row's verdict is then prefixed
"task solvable without the view (...)" (:func:`solvable_without_view`), naming the rule when
only one rule's threshold is that low.

Usage: ``geonav experiment table docs/results --readme README.md [--check]`` or
``python -m geonav.experiments.table docs/results --readme README.md [--check]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Any

from geonav.errors import ConfigError

START = "<!-- results-table:start -->"
END = "<!-- results-table:end -->"
COMMAND = "geonav experiment table docs/results --readme README.md"
RULES = (("ratio", "convergence", "verdict", "training-SR"),
         ("eval_ratio", "eval_convergence", "eval_verdict", "greedy-evaluation"))
THRESHOLD_KEYS = {"training-SR": "threshold", "greedy-evaluation": "eval_threshold"}
"""Each rule's success threshold in a summary's ``convergence`` record."""
FLOOR_TOLERANCE = 1e-12


def load_summaries(results_dir: str | Path) -> list[tuple[Path, dict[str, Any]]]:
    """(folder, summary) of every ``results_dir/*/summary.json``, by folder name."""
    root = Path(results_dir)
    if not root.is_dir():
        raise ConfigError(f"results folder {root} does not exist")
    out = []
    for path in sorted(root.glob("*/summary.json")):
        try:
            summary = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ConfigError(f"{path} is not valid JSON: {err}") from err
        if not isinstance(summary, dict) or not isinstance(summary.get("comparisons"), list):
            raise ConfigError(f"{path} has no 'comparisons' list; was it written by "
                              "geonav experiment run/report?")
        out.append((path.parent, summary))
    if not out:
        raise ConfigError(f"no */summary.json under {root}")
    return out


def _num(v: float) -> str:
    return f"{v:.0f}"


def _range(name: str, conv: dict[str, Any] | None) -> str:
    if not conv or not conv.get("n"):
        return f"{name} n/a"
    plus = "+" if conv.get("censored") else ""
    return f"{name} {_num(conv['min'])}-{_num(conv['max'])}{plus}"


def _ratio(a: str, b: str, ca: dict[str, Any] | None, cb: dict[str, Any] | None) -> str:
    """Our ratio b / a of median e* with censoring bounds, and the seed ranges."""
    ranges = f"({_range(b, cb)} vs {_range(a, ca)})"
    if not ca or not cb or not ca.get("n") or not cb.get("n") or not ca.get("median"):
        return f"n/a {ranges}"
    value = cb["median"] / ca["median"]
    ea, eb = bool(ca.get("median_censored")), bool(cb.get("median_censored"))
    if ea and eb:
        if ca.get("censored") == ca["n"] and cb.get("censored") == cb["n"]:
            return f"n/a, neither converged {ranges}"
        return f"n/a, both medians censored {ranges}"
    prefix = "<= " if ea else ">= " if eb else ""
    return f"{prefix}{value:.2f} {ranges}"


def _faster(verdict: str) -> str | None:
    """The method an 'effect shown: X converges in fewer episodes than Y' verdict names."""
    m = re.match(r"effect shown: (.+?) converges in fewer episodes than ", verdict or "")
    return m.group(1) if m else None


def rule_outcome(verdict: str | None, expected_faster: str | None) -> str:
    """'reproduced', 'not reproduced' or 'no effect' for one rule's verdict (without the
    paper's direction: 'effect shown (X faster)' or 'no effect')."""
    faster = _faster(verdict or "")
    if faster is None:
        return "no effect"
    if expected_faster is None:
        return f"effect shown ({faster} faster)"
    return "reproduced" if faster == expected_faster else "not reproduced"


SIZE_TOLERANCE = 2.0
"""How far (as a factor) our ratio may lie from the paper's for "reproduced" to stand."""


def _median_ratio(a: dict[str, Any] | None, b: dict[str, Any] | None) -> float | None:
    try:
        ra, rb = float(a["median"]), float(b["median"])  # type: ignore[index]
    except (TypeError, KeyError, ValueError):
        return None
    return rb / ra if ra > 0 else None


def size_qualified(verdict: str, ours: list[float | None], paper_ratio: float | None,
                   rules: list[str] | None = None) -> str:
    """``verdict``, or "direction reproduced, size not" when a rule's ratio lies more than
    :data:`SIZE_TOLERANCE` from the paper's. A "reproduced by the R rule only" verdict is
    judged on rule R's ratio (``ours[rules.index(R)]``) alone."""
    if not paper_ratio:
        return verdict
    one = re.fullmatch(r"reproduced by the (.+) rule only", verdict)
    if one and rules and one.group(1) in rules:
        r = ours[rules.index(one.group(1))]
        if r is not None and abs(math.log(r / paper_ratio)) > math.log(SIZE_TOLERANCE):
            return (f"direction reproduced by the {one.group(1)} rule only, size not "
                    f"(ours {r:.2f} vs the paper's {paper_ratio:.2f})")
        return verdict
    if verdict != "reproduced":
        return verdict
    off = [r for r in ours if r is not None and
           abs(math.log(r / paper_ratio)) > math.log(SIZE_TOLERANCE)]
    if not off:
        return verdict
    return (f"direction reproduced, size not (ours {', '.join(f'{r:.2f}' for r in ours if r)}"
            f" vs the paper's {paper_ratio:.2f})")


def combined_verdict(outcomes: dict[str, str]) -> str:
    """The row's verdict from the per-rule outcomes (see the module docstring)."""
    vals = list(outcomes.values())
    if "not reproduced" in vals:
        return "not reproduced"
    if vals and all(v == "reproduced" for v in vals):
        return "reproduced"
    if "reproduced" in vals:
        rule = next(r for r, v in outcomes.items() if v == "reproduced")
        return f"reproduced by the {rule} rule only"
    shown = sorted({v for v in vals if v.startswith("effect shown")})
    if shown:
        rules = [r for r, v in outcomes.items() if v.startswith("effect shown")]
        alone = f" by the {rules[0]} rule only" if len(rules) == 1 and len(vals) > 1 else ""
        return "; ".join(shown) + alone + " (no paper figure)"
    return "no effect shown at this budget"


def _rate(value: Any) -> float | None:
    """``value`` as a finite float, else None (absent, null or NaN in older summaries)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def view_blind_floor(random_walk_sr: float | None, blind_sr: float | None) -> float | None:
    """The lowest success threshold at which a rule can show navigation by the view.

    Args:
        random_walk_sr: success rate of uniform random actions on the task, in [0, 1].
        blind_sr: success rate of the best view-blind policy (knows the target, ignores
            the current view), in [0, 1].

    Returns:
        chance + (1 - chance) / 2 with chance the larger of the two rates present (as in
        :func:`geonav.convergence.noise_check`), or None when neither is given.
    """
    rates = [r for r in (random_walk_sr, blind_sr) if r is not None]
    if not rates:
        return None
    chance = max(rates)
    return chance + (1.0 - chance) / 2.0


VIEW_NEEDING_MAX_BLIND = 0.3
"""The view-blind success above which a comparison's task is not a view-needing one
(ALGORITHMS.md (f): tasks that are to show navigation by the view need <= 0.3)."""


def chance_cell(comp: dict[str, Any]) -> str:
    """The "chance: random walk / view-blind" cell, e.g. ``0.041 / 0.996``, with
    "(view-blind > 0.3)" where the task does not need the view by that standard."""
    rw, blind = _rate(comp.get("random_walk_sr")), _rate(comp.get("blind_sr"))
    if rw is None and blind is None:
        return "n/a"
    cell = " / ".join("n/a" if r is None else f"{r:.3f}" for r in (rw, blind))
    if blind is not None and blind > VIEW_NEEDING_MAX_BLIND:
        cell += f" (view-blind > {VIEW_NEEDING_MAX_BLIND:g})"
    return cell


def solvable_without_view(summary: dict[str, Any], comp: dict[str, Any]) -> str | None:
    """The "task solvable without the view (...)" mark when a rule's threshold is below
    :func:`view_blind_floor` of the comparison's chance figures, else None.

    Names the rule when only one rule's threshold is below the floor; None when the
    summary lacks the chance figures or the ``convergence`` thresholds.
    """
    rw, blind = _rate(comp.get("random_walk_sr")), _rate(comp.get("blind_sr"))
    floor = view_blind_floor(rw, blind)
    conv = summary.get("convergence") or {}
    if floor is None or not isinstance(conv, dict):
        return None
    low = {rule: v for rule, key in THRESHOLD_KEYS.items()
           if (v := _rate(conv.get(key))) is not None and v < floor - FLOOR_TOLERANCE}
    if not low:
        return None
    # the figure that sets the floor: view-blind unless the random walk does better
    chance = (f"view-blind {blind:.3f}" if blind is not None and (rw is None or blind >= rw)
              else f"random walk {rw:.3f}")
    if len(set(low.values())) == 1:
        thresholds = f"threshold {next(iter(low.values())):g}"
    else:
        thresholds = ", ".join(f"{THRESHOLD_KEYS[r]} {v:g}" for r, v in low.items())
    which = f" by the {next(iter(low))} rule" if len(low) < len(THRESHOLD_KEYS) else ""
    return (f"task solvable without the view{which} ({chance}; {thresholds} < "
            f"{floor:.3f})")


def _compute(comp: dict[str, Any], order: list[str]) -> str:
    if comp.get("compute_s") is not None:
        return (f"{comp['compute_s'] / 60:.1f} min over {comp.get('compute_units', 0)} units "
                "(training wall time, summed)")
    # a summary from before compute_s: the compared stages' own units only
    walls = [r.get("wall_total_s") for m in order for r in comp["methods"][m].get("runs", [])]
    walls = [w for w in walls if w is not None and not math.isnan(w)]
    if not walls:
        return "n/a"
    return (f">= {sum(walls) / 60:.1f} min over {len(walls)} units (compared stages only; "
            "the starting stages' time is not in this summary)")


def comparison_row(folder: Path, summary: dict[str, Any], comp: dict[str, Any],
                   link_base: Path) -> str:
    """One markdown table row for a comparison of a summary."""
    methods = comp.get("methods") or {}
    order = [m for m in (comp.get("order") or list(methods)) if m in methods]
    link = Path(os.path.relpath(folder / "report.md", link_base)).as_posix()
    claim = f"[{comp.get('claim') or comp['name']}]({link}) (`{folder.name}`)"
    chance = chance_cell(comp)
    mark = solvable_without_view(summary, comp)
    if len(order) < 2:
        verdict = f"{mark}: one method only" if mark else "one method only"
        return f"| {claim} | n/a | {chance} | n/a | n/a | {verdict} | {_compute(comp, order)} |"
    a, b = order[:2]
    paper = comp.get("paper") or {}
    expected = None
    if a in paper and b in paper and paper[a]:
        paper_text = f"{paper[b] / paper[a]:.2f} ({b} {paper[b]:g} vs {a} {paper[a]:g})"
        expected = b if paper[b] < paper[a] else a if paper[a] < paper[b] else None
    else:
        paper_text = "n/a (not in this summary)" if "paper" not in comp else "n/a"
    cells, outcomes, ours = [], {}, []
    for _, conv_key, verdict_key, rule in RULES:
        # a comparison that counts the starting stages (count_parents) compares totals
        ca, cb = (methods[x].get(f"{conv_key}_incl_parents") or methods[x].get(conv_key)
                  for x in (a, b))
        cells.append(_ratio(a, b, ca, cb))
        outcomes[rule] = rule_outcome(comp.get(verdict_key), expected)
        ours.append(_median_ratio(ca, cb))
    paper_ratio = paper[b] / paper[a] if expected is not None else None
    verdict = size_qualified(combined_verdict(outcomes), ours, paper_ratio, list(outcomes))
    running = sum(int(methods[m].get("in_progress") or 0) for m in order)
    if running:
        verdict += f" (interim: {running} run{'s' if running > 1 else ''} still going)"
    if mark:
        verdict = f"{mark}: {verdict}"
    return (f"| {claim} | {paper_text} | {chance} | {cells[0]} | {cells[1]} | "
            f"{verdict} | {_compute(comp, order)} |")


def render_table(results_dir: str | Path, link_base: str | Path = ".") -> str:
    """The markdown block (without the markers) for every summary under ``results_dir``;
    report links are relative to ``link_base`` (README's folder)."""
    base = Path(link_base).resolve()
    rows = [comparison_row(folder.resolve(), summary, comp, base)
            for folder, summary in load_summaries(results_dir) for comp in summary["comparisons"]]
    return "\n".join([
        f"_Generated by `{COMMAND}` from `docs/results/*/summary.json`; edit those, not "
        "this table. Chance: success of a random walk and of the best view-blind policy "
        "(knows the target, ignores the view). A rule whose success threshold is below "
        "chance + half the gap to 1 can be met without the view; its row's verdict then "
        "starts \"task solvable without the view\"._",
        "",
        "| claim | paper ratio | chance: random walk / view-blind | our ratio, training-SR e* "
        "(seed ranges) | our ratio, greedy-eval e* (seed ranges) | verdict | compute |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Ratio: e* of the second method over the first, medians over seeds; seed ranges: "
        "min-max of e* (`+`: some runs never converged and count at their budget). A "
        "verdict needs non-overlapping seed ranges (see each report).",
    ])


def replace_block(text: str, block: str, where: str = "README") -> str:
    """``text`` with the lines between :data:`START` and :data:`END` replaced by ``block``."""
    if text.count(START) != 1 or text.count(END) != 1:
        raise ConfigError(f"{where} needs exactly one {START} and one {END} line around the "
                          f"results table (found {text.count(START)} and {text.count(END)})")
    i, j = text.index(START), text.index(END)
    if j < i:
        raise ConfigError(f"{where}: {END} comes before {START}")
    return text[:i + len(START)] + "\n" + block + "\n" + text[j:]


def update_readme(results_dir: str | Path, readme: str | Path, *, check: bool = False
                  ) -> bool:
    """Rewrite README's table block from the summaries; returns whether it differed.
    With ``check`` nothing is written."""
    path = Path(readme)
    try:
        text = path.read_text()
    except FileNotFoundError as err:
        raise ConfigError(f"README {path} does not exist") from err
    new = replace_block(text, render_table(results_dir, path.parent), str(path))
    if new == text:
        return False
    if not check:
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(new)
        os.replace(tmp, path)
    return True


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("results", help="results folder holding */summary.json (docs/results)")
    p.add_argument("--readme", default=None, metavar="README.md",
                   help="rewrite the table between the results-table marker comments of this "
                        "file (without it the table is printed)")
    p.add_argument("--check", action="store_true",
                   help="with --readme: write nothing, exit 1 when the table is out of date")


def run(args: argparse.Namespace) -> int:
    """Handler of ``geonav experiment table``."""
    if args.readme is None:
        if args.check:
            raise ConfigError("--check needs --readme")
        print(render_table(args.results))
        return 0
    differs = update_readme(args.results, args.readme, check=args.check)
    if args.check:
        if differs:
            print(f"{args.readme}: the results table differs from {args.results}/*/summary.json;"
                  f" run: geonav experiment table {args.results} --readme {args.readme}",
                  file=sys.stderr)
            return 1
        print(f"{args.readme}: the results table matches {args.results}/*/summary.json")
        return 0
    print(f"{args.readme}: results table {'updated' if differs else 'already up to date'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m geonav.experiments.table",
                                description=__doc__.split("\n\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
