"""README's results table from docs/results/*/summary.json (geonav.experiments.table)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from geonav.errors import ConfigError
from geonav.experiments import table

REPO = Path(__file__).resolve().parents[1]


def test_readme_table_agrees_with_docs_results():
    """The committed README's table is what docs/results/*/summary.json give: after a new
    result lands, run `geonav experiment table docs/results --readme README.md`."""
    assert table.update_readme(REPO / "docs" / "results", REPO / "README.md",
                               check=True) is False, (
        "README.md's results table is out of date; run: " + table.COMMAND)


def _conv(values, censored=0, median_censored=False):
    return {"n": len(values), "median": sorted(values)[len(values) // 2], "min": min(values),
            "max": max(values), "censored": censored, "median_censored": median_censored}


CONVERGENCE = {"window": 500, "threshold": 0.95, "hold": 0.9, "eval_threshold": 0.95}


def _summary(verdict, eval_verdict, paper=None, scratch=(900, 1000, 1200),
             transfer=(100, 120, 150), convergence=CONVERGENCE, **extra):
    comp = {"name": "transfer A to B", "part": "transfer", "order": ["scratch", "transfer"],
            "methods": {"transfer": {"convergence": _conv(transfer),
                                     "eval_convergence": _conv(transfer)},
                        "scratch": {"convergence": _conv(scratch),
                                    "eval_convergence": _conv(scratch)}},
            "verdict": verdict, "eval_verdict": eval_verdict,
            "compute_s": 600.0, "compute_units": 9, **extra}
    if paper is not None:
        comp["paper"] = paper
    return {"name": "x", "convergence": convergence, "comparisons": [comp]}


SHOWN = ("effect shown: transfer converges in fewer episodes than scratch (seed ranges "
         "100-150 vs 900-1200 do not overlap)")
OPPOSITE = ("effect shown: scratch converges in fewer episodes than transfer (seed ranges "
            "1-2 vs 3-4 do not overlap)")
NONE = "no effect shown at this budget (seed ranges 1-5 and 2-6 overlap)"
PAPER = {"transfer": 2000, "scratch": 50000}


@pytest.fixture()
def results(tmp_path):
    root = tmp_path / "docs" / "results"
    (root / "part5").mkdir(parents=True)
    (root / "part5" / "summary.json").write_text(json.dumps(_summary(SHOWN, SHOWN, PAPER)))
    readme = tmp_path / "README.md"
    readme.write_text(f"# t\n\nintro\n\n{table.START}\nold\n{table.END}\n\nafter\n")
    return root, readme


def test_row_has_claim_ratios_ranges_verdict_and_compute(results):
    root, readme = results
    assert table.update_readme(root, readme) is True
    text = readme.read_text()
    assert text.startswith("# t\n\nintro\n\n") and text.endswith(f"{table.END}\n\nafter\n")
    assert "\nold\n" not in text  # the old block is gone
    row = next(ln for ln in text.splitlines() if ln.startswith("| [transfer A to B]"))
    assert "| chance: random walk / view-blind |" in text
    assert row == ("| [transfer A to B](docs/results/part5/report.md) (`part5`) | "
                   "0.04 (transfer 2000 vs scratch 50000) | n/a | "
                   "0.12 (transfer 100-150 vs scratch 900-1200) | "
                   "0.12 (transfer 100-150 vs scratch 900-1200) | direction reproduced, size "
                   "not (ours 0.12, 0.12 vs the paper's 0.04) | "
                   "10.0 min over 9 units (training wall time, summed) |")
    # idempotent, and --check agrees
    assert table.update_readme(root, readme) is False
    assert table.update_readme(root, readme, check=True) is False


def test_check_fails_when_a_summary_changes(results):
    root, readme = results
    table.update_readme(root, readme)
    (root / "part5" / "summary.json").write_text(json.dumps(_summary(NONE, NONE, PAPER)))
    before = readme.read_text()
    assert table.main([str(root), "--readme", str(readme), "--check"]) == 1
    assert readme.read_text() == before  # --check writes nothing
    assert table.main([str(root), "--readme", str(readme)]) == 0
    assert "| no effect shown at this budget |" in readme.read_text()
    assert table.main([str(root), "--readme", str(readme), "--check"]) == 0


@pytest.mark.parametrize(("verdict", "eval_verdict", "paper", "want"), [
    (SHOWN, SHOWN, {"transfer": 120, "scratch": 1000}, "reproduced"),
    (SHOWN, SHOWN, PAPER, "direction reproduced, size not (ours 0.12, 0.12 vs the paper's 0.04)"),
    (SHOWN, NONE, {"transfer": 120, "scratch": 1000}, "reproduced by the training-SR rule only"),
    (SHOWN, NONE, PAPER, "direction reproduced by the training-SR rule only, size not (ours "
                         "0.12 vs the paper's 0.04)"),
    (NONE, SHOWN, PAPER, "direction reproduced by the greedy-evaluation rule only, size not "
                         "(ours 0.12 vs the paper's 0.04)"),
    (OPPOSITE, SHOWN, PAPER, "not reproduced"),
    (NONE, NONE, PAPER, "no effect shown at this budget"),
    (SHOWN, NONE, None, "effect shown (transfer faster) by the training-SR rule only (no "
                        "paper figure)"),
    (SHOWN, SHOWN, None, "effect shown (transfer faster) (no paper figure)"),
])
def test_verdicts(verdict, eval_verdict, paper, want, tmp_path):
    (tmp_path / "r" / "a").mkdir(parents=True)
    (tmp_path / "r" / "a" / "summary.json").write_text(
        json.dumps(_summary(verdict, eval_verdict, paper)))
    assert f"| {want} |" in table.render_table(tmp_path / "r", tmp_path)


def test_censored_ratios_are_bounds(tmp_path):
    s = _summary(NONE, NONE, PAPER)
    s["comparisons"][0]["methods"]["scratch"]["convergence"] = _conv((5000, 5000, 5000), 3,
                                                                     True)
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "summary.json").write_text(json.dumps(s))
    assert "<= 0.02 (transfer 100-150 vs scratch 5000-5000+)" in table.render_table(tmp_path)


def test_censored_medians_say_whether_any_run_converged(tmp_path):
    """Both medians censored: "neither converged" only when no run of either method met
    the rule; a method with some converged runs makes it "both medians censored"."""
    s = _summary(NONE, NONE, PAPER)
    methods = s["comparisons"][0]["methods"]
    methods["scratch"]["convergence"] = _conv((5000, 5000, 5000), 3, True)
    methods["transfer"]["convergence"] = _conv((5000, 5000, 5000), 3, True)
    methods["scratch"]["eval_convergence"] = _conv((5000, 5000, 5000), 3, True)
    methods["transfer"]["eval_convergence"] = _conv((4750, 5000, 5000), 2, True)
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "summary.json").write_text(json.dumps(s))
    text = table.render_table(tmp_path)
    assert "| n/a, neither converged (transfer 5000-5000+ vs scratch 5000-5000+) |" in text
    assert "| n/a, both medians censored (transfer 4750-5000+ vs scratch 5000-5000+) |" in text


def test_claim_label_names_the_row(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "summary.json").write_text(
        json.dumps(_summary(SHOWN, SHOWN, PAPER, claim="5. transfer A -> B")))
    assert "| [5. transfer A -> B](a/report.md) (`a`) |" in table.render_table(tmp_path,
                                                                              tmp_path)


def test_old_summaries_and_errors(tmp_path):
    s = _summary(NONE, NONE)
    comp = s["comparisons"][0]
    for key in ("order", "compute_s", "compute_units"):
        del comp[key]
    comp["methods"]["scratch"]["runs"] = [{"wall_total_s": 60.0}, {"wall_total_s": 120.0}]
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "summary.json").write_text(json.dumps(s))
    text = table.render_table(tmp_path)
    # the method order falls back to the methods' order; paper figures are said missing
    assert "n/a (not in this summary) | n/a | 8.33 (scratch 900-1200 vs transfer 100-150)" in text
    assert ">= 3.0 min over 2 units (compared stages only" in text
    with pytest.raises(ConfigError, match="no \\*/summary.json"):
        table.render_table(tmp_path / "a")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "summary.json").write_text("{")
    with pytest.raises(ConfigError, match="not valid JSON"):
        table.render_table(tmp_path)
    readme = tmp_path / "R.md"
    readme.write_text("no markers\n")
    with pytest.raises(ConfigError, match="needs exactly one"):
        table.replace_block(readme.read_text(), "x")
    with pytest.raises(ConfigError, match="comes before"):
        table.replace_block(f"{table.END}\n{table.START}\n", "x")


def test_a_ratio_far_from_the_papers_is_direction_only():
    from geonav.experiments.table import size_qualified

    assert size_qualified("reproduced", [1.8, 2.1], 2.0) == "reproduced"
    assert size_qualified("reproduced", [1.22, 1.20], 5.0) == (
        "direction reproduced, size not (ours 1.22, 1.20 vs the paper's 5.00)")
    assert size_qualified("reproduced", [1.9, None], 2.0) == "reproduced"
    assert size_qualified("no effect shown at this budget", [1.0], 5.0) == \
        "no effect shown at this budget"
    # one rule alone: judged on that rule's ratio (transfer-corr: 1.39 by the greedy rule
    # against the paper's 25 read "reproduced by the greedy-evaluation rule only")
    rules = ["training-SR", "greedy-evaluation"]
    assert size_qualified("reproduced by the greedy-evaluation rule only", [0.76, 1.39], 25.0,
                          rules) == ("direction reproduced by the greedy-evaluation rule only, "
                                     "size not (ours 1.39 vs the paper's 25.00)")
    assert size_qualified("reproduced by the training-SR rule only", [20.0, 1.0], 25.0,
                          rules) == "reproduced by the training-SR rule only"


def test_an_effect_by_one_rule_without_a_paper_figure_says_which_rule():
    from geonav.experiments.table import combined_verdict

    assert combined_verdict({"training-SR": "effect shown (a faster)",
                             "greedy-evaluation": "no effect"}) == \
        "effect shown (a faster) by the training-SR rule only (no paper figure)"
    assert combined_verdict({"training-SR": "effect shown (a faster)",
                             "greedy-evaluation": "effect shown (a faster)"}) == \
        "effect shown (a faster) (no paper figure)"


def _render_one(tmp_path, summary):
    (tmp_path / "r" / "a").mkdir(parents=True)
    (tmp_path / "r" / "a" / "summary.json").write_text(json.dumps(summary))
    text = table.render_table(tmp_path / "r", tmp_path)
    return next(ln for ln in text.splitlines() if ln.startswith("| [transfer A to B]"))


def test_view_blind_floor_is_chance_plus_half_the_gap():
    assert table.view_blind_floor(0.04, 0.996) == pytest.approx(0.998)
    assert table.view_blind_floor(0.5, 0.3) == pytest.approx(0.75)  # the random walk's
    assert table.view_blind_floor(None, 0.3) == pytest.approx(0.65)
    assert table.view_blind_floor(None, None) is None


def test_a_task_the_view_blind_policy_solves_marks_the_verdict(tmp_path):
    """blind 0.996: floor 0.998 lies above both thresholds (0.95), so no verdict on this
    task can show navigation by the view."""
    s = _summary(SHOWN, SHOWN, {"transfer": 120, "scratch": 1000}, random_walk_sr=0.0413,
                 blind_sr=0.9957)
    assert table.solvable_without_view(s, s["comparisons"][0]) == (
        "task solvable without the view (view-blind 0.996; threshold 0.95 < 0.998)")
    row = _render_one(tmp_path, s)
    assert "| 0.041 / 0.996 (view-blind > 0.3) |" in row
    assert ("| task solvable without the view (view-blind 0.996; threshold 0.95 < 0.998): "
            "reproduced |") in row


def test_a_task_with_a_weak_view_blind_policy_is_not_marked(tmp_path):
    s = _summary(SHOWN, SHOWN, {"transfer": 120, "scratch": 1000}, random_walk_sr=0.04,
                 blind_sr=0.3)
    assert table.solvable_without_view(s, s["comparisons"][0]) is None
    row = _render_one(tmp_path, s)
    assert "| 0.040 / 0.300 | 0.12 (" in row and "| reproduced |" in row
    assert "without the view" not in row


def test_only_the_rule_whose_threshold_is_below_the_floor_is_named():
    conv = dict(CONVERGENCE, threshold=0.8, eval_threshold=0.99)  # floor 0.85
    s = _summary(SHOWN, SHOWN, convergence=conv, random_walk_sr=0.04, blind_sr=0.7)
    assert table.solvable_without_view(s, s["comparisons"][0]) == (
        "task solvable without the view by the training-SR rule (view-blind 0.700; "
        "threshold 0.8 < 0.850)")
    conv = dict(CONVERGENCE, threshold=0.8, eval_threshold=0.82)
    s = _summary(SHOWN, SHOWN, convergence=conv, random_walk_sr=0.04, blind_sr=0.7)
    assert table.solvable_without_view(s, s["comparisons"][0]) == (
        "task solvable without the view (view-blind 0.700; threshold 0.8, eval_threshold "
        "0.82 < 0.850)")
    # a threshold at the floor is not below it
    conv = dict(CONVERGENCE, threshold=0.85, eval_threshold=0.85)
    s = _summary(SHOWN, SHOWN, convergence=conv, random_walk_sr=0.04, blind_sr=0.7)
    assert table.solvable_without_view(s, s["comparisons"][0]) is None


def test_a_summary_without_the_chance_figures_says_na_and_has_no_mark(tmp_path):
    s = _summary(SHOWN, SHOWN, {"transfer": 120, "scratch": 1000})
    assert table.solvable_without_view(s, s["comparisons"][0]) is None
    row = _render_one(tmp_path, s)
    assert "| 0.12 (transfer 120 vs scratch 1000) | n/a | 0.12 (" in row
    assert row.endswith("| reproduced | 10.0 min over 9 units (training wall time, summed) |")
    # the random walk alone (a summary from before blind_sr; NaN reads as missing)
    s = _summary(SHOWN, SHOWN, random_walk_sr=0.041, blind_sr=float("nan"))
    assert table.chance_cell(s["comparisons"][0]) == "0.041 / n/a"
    assert table.solvable_without_view(s, s["comparisons"][0]) is None
    # no convergence thresholds in the summary: nothing to judge
    s = _summary(SHOWN, SHOWN, convergence=None, random_walk_sr=0.04, blind_sr=0.996)
    assert table.solvable_without_view(s, s["comparisons"][0]) is None


def test_the_mark_keeps_update_readme_idempotent(results):
    root, readme = results
    (root / "part5" / "summary.json").write_text(json.dumps(
        _summary(SHOWN, SHOWN, PAPER, random_walk_sr=0.04, blind_sr=0.996)))
    assert table.update_readme(root, readme) is True
    text = readme.read_text()
    assert text.count("task solvable without the view (view-blind") == 1
    assert "| 0.040 / 0.996 (view-blind > 0.3) |" in text
    assert table.update_readme(root, readme) is False
    assert table.update_readme(root, readme, check=True) is False
    assert readme.read_text() == text


def test_chance_cell_flags_tasks_that_do_not_need_the_view():
    assert table.chance_cell({"random_walk_sr": 0.031, "blind_sr": 0.653}) == \
        "0.031 / 0.653 (view-blind > 0.3)"
    assert table.chance_cell({"random_walk_sr": 0.056, "blind_sr": 0.072}) == "0.056 / 0.072"
    assert table.chance_cell({"random_walk_sr": 0.2, "blind_sr": 0.3}) == "0.200 / 0.300"
