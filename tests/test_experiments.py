"""The transfer experiment runner end to end on a tiny config (real training, seconds)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest

from geonav.errors import ConfigError, ReportError
from geonav.experiments.config import load_config, parse_config

TINY = """
name = "tiny"
seeds = [0, 1]
eval_starts = 8

[convergence]          # budgets below 2 W: never met, so the noise check accepts it
window = 100
threshold = 0.97
hold = 0.9
eval_threshold = 0.97

[scenes.A]
synthetic = "residential"
size_m = 300.0
gsd_m = 1.0

[scenes.B]
synthetic = "campus"
size_m = 300.0
gsd_m = 1.0
seed = 1

[tasks.A_meta]
scene = "A"
kind = "meta"
count = 2
size_m = 45.0
alt_m = 30.0
step_m = 15.0
max_steps = 15
obs_size_px = 24

[tasks.B_target]
scene = "B"
kind = "meta"
count = 1
size_m = 45.0
alt_m = 30.0
step_m = 15.0
max_steps = 15
obs_size_px = 24

[stages.pre]
mode = "train"
tasks = "A_meta"
algo = "a3c"
episodes = EPISODES
workers = 0
lr = 0.001
checkpoint_every = 10

[stages.transfer]
mode = "train"
tasks = "B_target"
algo = "a3c"
init = "pre"
episodes = EPISODES
workers = 0
lr = 0.001
checkpoint_every = 10

[stages.scratch]
mode = "train"
tasks = "B_target"
algo = "a3c"
episodes = EPISODES
workers = 0
lr = 0.001
checkpoint_every = 10

[[compare]]
name = "transfer vs scratch"
part = "transfer"
methods = ["scratch", "transfer"]
paper = { transfer = 2000, scratch = 50000 }

[flight]
stage = "transfer"
"""


def _write(tmp_path: Path, episodes: int) -> Path:
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY.replace("EPISODES", str(episodes)))
    return cfg


def _geonav(*args: str, cwd: Path) -> list[str]:
    return [sys.executable, "-m", "geonav.cli", *args]


def test_tiny_experiment_end_to_end(tmp_path):
    cfg = _write(tmp_path, 40)
    run = subprocess.run(_geonav("experiment", "run", str(cfg), "--out", "runs", "--jobs", "2",
                                 cwd=tmp_path), cwd=tmp_path, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    root = tmp_path / "runs" / "tiny"
    report = (root / "report.md").read_text()
    for section in ("# Experiment `tiny`", "## transfer vs scratch", "| scratch |",
                    "| transfer |", "Ratio transfer / scratch", "the paper's: 0.04",
                    "curves-transfer-vs-scratch.png", "trajectories-transfer-vs-scratch.png",
                    "## Stages"):
        assert section in report, section
    assert (root / "curves-transfer-vs-scratch.png").stat().st_size > 10_000
    summary = json.loads((root / "summary.json").read_text())
    comp = summary["comparisons"][0]
    for method in ("scratch", "transfer"):
        rec = comp["methods"][method]
        assert rec["convergence"]["n"] == 2
        assert 0.0 <= rec["final_greedy_sr"] <= 1.0 and 0.0 <= rec["final_sampled_sr"] <= 1.0
        assert rec["eval_convergence"]["n"] == 2
        assert len(rec["runs"]) == 2 and all(r["episodes"] == 40 for r in rec["runs"])
    # what README's results table reads (geonav.experiments.table)
    assert comp["order"] == ["scratch", "transfer"] and comp["part"] == "transfer"
    assert comp["claim"] == "transfer vs scratch"  # no claim label: the name
    assert comp["paper_ratio"] == pytest.approx(0.04)
    assert comp["compute_units"] == 6 and comp["compute_s"] > 0  # pre, scratch, transfer x 2
    readme = tmp_path / "README.md"
    readme.write_text("# x\n<!-- results-table:start -->\n<!-- results-table:end -->\n")
    table = subprocess.run(_geonav("experiment", "table", "runs", "--readme", "README.md",
                                   cwd=tmp_path), cwd=tmp_path, capture_output=True,
                           text=True, timeout=120)
    assert table.returncode == 0, table.stderr[-3000:]
    assert "| [transfer vs scratch](runs/tiny/report.md) (`tiny`) | 0.04 (transfer 2000 vs " \
        "scratch 50000) |" in readme.read_text()
    # transfer started from pre's final weights, scratch did not
    tr = json.loads((root / "units/transfer/seed-0/config.json").read_text())
    assert tr["algorithm"] == "a3c"
    from geonav.experiments.runner import read_result

    stored = json.loads((root / "units/transfer/seed-1/result.json").read_text())
    assert stored["checkpoint"] == "units/transfer/seed-1/checkpoints/final.pt"  # relocatable
    result = read_result(root / "units/transfer/seed-1")
    assert Path(result["checkpoint"]).exists() and result["eval"]["starts"] == 8
    assert 0.0 < result["eval"]["random_walk_sr"] < 1.0 and "zero_shot" in result["eval"]
    assert "Chance on this task" in report and "Verdict (greedy-evaluation rule)" in report
    assert "IQM" in report and "stratified-bootstrap" in report
    assert "### Starting stage `pre`" in report
    assert (root / "units/transfer/seed-0/eval.csv").read_text().startswith("episode,")
    # the transferred policy flew its task through the MAVLink emulator, and landed
    assert "## Flight (MAVLink emulator)" in report
    flight = json.loads((root / "flight" / "summary.json").read_text())
    assert flight["end_action"] == "land" and flight["disarmed"]
    steps = (root / "flight" / "flight.jsonl").read_text().strip().splitlines()
    assert flight["steps"] >= 1 and len(steps) >= flight["steps"]
    # runs without evaluation rows (eval_every = 0) have no evaluation e*, not a censored
    # one at their budget that the verdict would compare
    for seed in (0, 1):
        (root / f"units/scratch/seed-{seed}/eval.csv").unlink()
    rep = subprocess.run(_geonav("experiment", "report", str(cfg), "--out", "runs",
                                 cwd=tmp_path), cwd=tmp_path, capture_output=True, text=True,
                         timeout=300)
    assert rep.returncode == 0, rep.stderr[-3000:]
    comp = json.loads((root / "summary.json").read_text())["comparisons"][0]
    assert comp["methods"]["scratch"]["eval_convergence"]["n"] == 0
    assert comp["methods"]["transfer"]["eval_convergence"]["n"] == 2
    assert comp["eval_verdict"] == "no effect shown (runs missing)"
    # an interim report of a run still going: a unit without result.json, its metrics cut
    # mid-line, counts (with --partial only) at the episode it has reached
    unit = root / "units/transfer/seed-1"
    (unit / "result.json").unlink()
    rows = (unit / "metrics.csv").read_text().splitlines()
    (unit / "metrics.csv").write_text("\n".join(rows[:26]) + "\n" + rows[26][:5])
    for partial in (False, True):
        rep = subprocess.run(_geonav("experiment", "report", str(cfg), "--out", "runs",
                                     *(["--partial"] if partial else []), cwd=tmp_path),
                             cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert rep.returncode == 0, rep.stderr[-3000:]
        summary = json.loads((root / "summary.json").read_text())
        rec = summary["comparisons"][0]["methods"]["transfer"]
        report = (root / "report.md").read_text()
        if not partial:
            assert rec["convergence"]["n"] == 1 and summary["in_progress"] == []
            assert "Interim report" not in report
            continue
        assert summary["in_progress"] == ["transfer/seed-1 (25 episodes)"]
        assert rec["convergence"]["n"] == 2 and rec["in_progress"] == 1
        running = [r for r in rec["runs"] if r["in_progress"]]
        assert [(r["seed"], r["episodes"], r["conv"]["censored"]) for r in running] == \
            [(1, 25, True)]
        assert "**Interim report: 1 unit(s) still running**" in report
        assert "(1 of 2 still running)" in report and "| 1/2 (+1 running) |" in report
    table = subprocess.run(_geonav("experiment", "table", "runs", "--readme", "README.md",
                                   cwd=tmp_path), cwd=tmp_path, capture_output=True,
                           text=True, timeout=120)
    assert table.returncode == 0, table.stderr[-3000:]
    assert "(interim: 1 run still going)" in readme.read_text()
    # --only PART reports that part's comparisons only, not every other part whose stages
    # it happens to run (configs/paper.toml's wild-aug reuses all of wild's stages)
    cfg.write_text(cfg.read_text().replace("[flight]", """[[compare]]
name = "scratch alone"
part = "scratch-only"
methods = ["scratch"]

[flight]"""))
    for only, names in ((["--only", "scratch-only"], ["scratch alone"]),
                        ([], ["transfer vs scratch", "scratch alone"])):
        rep = subprocess.run(_geonav("experiment", "report", str(cfg), "--out", "runs",
                                     *only, cwd=tmp_path), cwd=tmp_path,
                             capture_output=True, text=True, timeout=300)
        assert rep.returncode == 0, rep.stderr[-3000:]
        summary = json.loads((root / "summary.json").read_text())
        assert [c["claim"] for c in summary["comparisons"]] == names
        assert ("## transfer vs scratch" in (root / "report.md").read_text()) == (not only)
    # a run made with --seeds is reported with the same --seeds (part 1 ran 5 seeds of a
    # 3-seed config); here a subset
    rep = subprocess.run(_geonav("experiment", "report", str(cfg), "--out", "runs", "--seeds",
                                 "0", "--only", "transfer", cwd=tmp_path), cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert rep.returncode == 0, rep.stderr[-3000:]
    comp = json.loads((root / "summary.json").read_text())["comparisons"][0]
    assert [r["seed"] for r in comp["methods"]["scratch"]["runs"]] == [0]
    assert "seeds [0]." in (root / "report.md").read_text()


def test_read_success_skips_only_a_cut_last_row(tmp_path):
    from geonav.experiments.report import read_success

    head = "episode,success,elapsed_s,length,shortest_path\n"
    rows = [f"{i},{i % 2},{0.1 * i},5,4" for i in range(1, 6)]
    f = tmp_path / "metrics.csv"
    f.write_text(head + "\n".join(rows) + "\n6,")  # a run killed mid-line
    succ, wall, length, short = read_success(f)
    assert succ.tolist() == [True, False, True, False, True] and len(wall) == 5
    f.write_text(head + "\n".join(rows[:2] + ["3,x,0.3,5,4"] + rows[3:]) + "\n")
    with pytest.raises(ReportError, match="line 4 cannot be read"):
        read_success(f)  # a bad row in the middle is corruption, not a cut curve


def test_interim_curriculum_unit_counts_only_on_its_last_level(tmp_path):
    from geonav.experiments.report import in_progress_result

    state = {"curriculum": {"levels_m": [75.0, 45.0, 15.0]},
             "stages": [{"alt_m": 75.0, "episodes": 300}]}
    (tmp_path / "curriculum.json").write_text(json.dumps(state))
    (tmp_path / "stage_1_45m").mkdir()
    (tmp_path / "stage_1_45m" / "metrics.csv").write_text("episode,success\n1,0\n")
    assert in_progress_result(tmp_path) is None  # still on 45 m: no e* at 15 m yet
    state["stages"].append({"alt_m": 45.0, "episodes": 40})
    (tmp_path / "curriculum.json").write_text(json.dumps(state))
    assert in_progress_result(tmp_path) is None  # 15 m not started
    (tmp_path / "stage_2_15m").mkdir()
    (tmp_path / "stage_2_15m" / "metrics.csv").write_text("episode,success\n1,0\n")
    got = in_progress_result(tmp_path)
    assert got is not None and got["episodes_before_metrics"] == 340 and got["in_progress"]
    assert got["metrics"] == str(tmp_path / "stage_2_15m" / "metrics.csv")
    assert in_progress_result(tmp_path / "nothing") is None


def test_resume_after_kill_skips_finished_units(tmp_path):
    cfg = _write(tmp_path, 150)
    root = tmp_path / "runs" / "tiny"
    proc = subprocess.Popen(_geonav("experiment", "run", str(cfg), "--out", "runs", "--jobs", "1",
                                    "--only", "transfer", "--fly", "no", cwd=tmp_path),
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    first_done = None
    deadline = time.time() + 240
    try:
        while time.time() < deadline:
            done = sorted(root.glob("units/*/seed-*/result.json"))
            ckpts = [p for p in root.glob("units/*/seed-*/checkpoints/latest.pt")
                     if not (p.parent.parent / "result.json").exists()]
            if done and ckpts:
                first_done = done[0]
                break
            time.sleep(0.2)
        assert first_done is not None, "no unit finished in time"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    mtime = first_done.stat().st_mtime_ns
    unfinished = [p.parent.parent for p in root.glob("units/*/seed-*/checkpoints/latest.pt")
                  if not (p.parent.parent / "result.json").exists()]
    assert unfinished
    rerun = subprocess.run(_geonav("experiment", "run", str(cfg), "--out", "runs", "--jobs", "2",
                                   "--only", "transfer", "--fly", "no", cwd=tmp_path), cwd=tmp_path,
                           capture_output=True, text=True, timeout=400)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert first_done.stat().st_mtime_ns == mtime  # finished unit skipped
    resumed = json.loads((unfinished[0] / "config.json").read_text())
    assert resumed["resume"] and resumed["start_episode"] > 0  # continued from its checkpoint
    assert len(list(root.glob("units/*/seed-*/result.json"))) == 6
    rows = (unfinished[0] / "metrics.csv").read_text().strip().splitlines()
    episodes = [int(r.split(",")[0]) for r in rows[1:]]
    assert episodes[-1] == 150 and len(set(episodes)) == len(episodes)
    # training time accumulates across the resume instead of restarting at zero
    header = rows[0].split(",")
    col = header.index("elapsed_s")
    elapsed = [float(r.split(",")[col]) for r in rows[1:]]
    assert all(b >= a for a, b in zip(elapsed, elapsed[1:], strict=False))


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "none.toml")
    (tmp_path / "bad.toml").write_text("name = [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(tmp_path / "bad.toml")
    base = {"scenes": {"A": {"synthetic": "residential"}},
            "tasks": {"t": {"scene": "A"}},
            "stages": {"s": {"mode": "train", "tasks": "t"}}}
    parse_config(base)
    with pytest.raises(ConfigError, match="unknown top-level"):
        parse_config({**base, "oops": 1})
    with pytest.raises(ConfigError, match="mode = 'fly'"):
        parse_config({**base, "stages": {"s": {"mode": "fly", "tasks": "t"}}})
    with pytest.raises(ConfigError, match="init = 'x' is not a stage"):
        parse_config({**base, "stages": {"s": {"mode": "train", "tasks": "t", "init": "x"}}})
    with pytest.raises(ConfigError, match="cycle"):
        parse_config({**base, "stages": {"s": {"mode": "train", "tasks": "t", "init": "u"},
                                         "u": {"mode": "train", "tasks": "t", "init": "s"}}})
    with pytest.raises(ConfigError, match="not among the scenes"):
        parse_config({**base, "tasks": {"t": {"scene": "Z"}}})
    with pytest.raises(ConfigError, match="unknown key"):
        parse_config({**base, "scenes": {"A": {"synthetic": "residential", "colour": 1}}})
    cfg = parse_config({**base, "compare": [{"name": "c", "part": "p", "methods": ["s"]}]})
    with pytest.raises(ConfigError, match="unknown part"):
        cfg.stages_for(["q"])


def test_shipped_configs_parse():
    root = Path(__file__).resolve().parent.parent / "configs"
    files = sorted(root.glob("*.toml"))
    assert files, "configs/ must ship experiment configs"
    for f in files:
        cfg = load_config(f)
        assert cfg.compare and cfg.stages
        for part in cfg.parts():
            assert cfg.stages_for([part])


def test_paper_tasks_are_not_solved_by_chance():
    """Issue 12: every task set of the paper protocol keeps only targets from which a
    random walk succeeds at most 5 % of the time (the sampler enforces the cap), or
    (issue 29, the *_view task sets) only targets that need the view: view-blind <= 0.3."""
    cfg = load_config(Path(__file__).resolve().parent.parent / "configs" / "paper.toml")
    for key, spec in cfg.tasks.items():
        if key.endswith("_view"):
            assert spec.max_blind is not None and spec.max_blind <= 0.3, key
        else:
            assert spec.max_random_walk is not None and spec.max_random_walk <= 0.05, key
    quick = load_config(Path(__file__).resolve().parent.parent / "configs" / "quick.toml")
    for key, spec in quick.tasks.items():
        assert spec.max_blind is not None and spec.max_blind <= 0.3, key


def test_a_part_makes_only_its_inputs_and_resumes_past_edits_elsewhere(tmp_path):
    """--only PART synthesises only the scenes and task sets its stages train on, and an
    edit of a stage outside the part does not block resuming it (issue 12: parts of
    configs/paper.toml are run one at a time)."""
    from geonav.experiments.runner import _experiment_part, prepare_inputs

    extra = TINY.replace("EPISODES", "20") + """
[scenes.C]
synthetic = "wild"
size_m = 300.0
gsd_m = 1.0

[tasks.C_target]
scene = "C"
kind = "meta"
size_m = 45.0
alt_m = 30.0
step_m = 15.0
max_steps = 15
obs_size_px = 24

[stages.wild]
mode = "train"
tasks = "C_target"
algo = "a3c"
episodes = 20
workers = 0

[[compare]]
name = "wild"
part = "wild"
methods = ["wild"]
"""
    import tomllib

    cfg = parse_config(tomllib.loads(extra), "extra")
    stages = cfg.stages_for(["wild"])
    assert stages == ["wild"]
    scenes, tasks = prepare_inputs(cfg, tmp_path, stages=stages)
    assert set(scenes) == {"C"} and set(tasks) == {"C_target"}
    assert sorted(p.name for p in (tmp_path / "scenes").iterdir()) == ["C"]
    edited = tomllib.loads(extra)
    edited["stages"]["scratch"]["lr"] = 0.01  # a stage of another part
    other = parse_config(edited, "edited")
    assert _experiment_part(cfg.to_dict(), stages) == _experiment_part(other.to_dict(), stages)
    assert _experiment_part(cfg.to_dict()) != _experiment_part(other.to_dict())
    edited["stages"]["wild"]["lr"] = 0.01  # the part's own stage: refused to resume
    mine = parse_config(edited, "mine")
    assert _experiment_part(cfg.to_dict(), stages) != _experiment_part(mine.to_dict(), stages)

    # a part added to the config since the run began is new, not an edit: the run folder
    # takes it (its stage, task set and scene were not in the run's config.json)
    from geonav.experiments.runner import _same_part

    base = parse_config(tomllib.loads(TINY.replace("EPISODES", "20")), "base").to_dict()
    assert _same_part(_experiment_part(base, stages), _experiment_part(cfg.to_dict(), stages))
    assert _same_part(_experiment_part(base), _experiment_part(cfg.to_dict()))
    assert not _same_part(_experiment_part(cfg.to_dict(), stages),
                          _experiment_part(mine.to_dict(), stages))
    assert not _same_part(_experiment_part(cfg.to_dict()), _experiment_part(other.to_dict()))
    conv = cfg.to_dict()
    conv["convergence"] = dict(conv["convergence"], window=7)
    assert not _same_part(_experiment_part(cfg.to_dict(), stages),
                          _experiment_part(conv, stages))

    # ... unless the folder already holds units of that stage: config.json is rewritten by
    # every run, so a stage dropped from the config, run around and added again with other
    # settings would otherwise resume its old units unchecked
    from geonav.experiments.runner import _open_run

    run_root = tmp_path / "runs"
    (run_root / cfg.name / "units" / "wild" / "seed-0").mkdir(parents=True)
    (run_root / cfg.name / "config.json").write_text(json.dumps(base))
    with pytest.raises(ConfigError, match="units/wild.*does not name"):
        _open_run(cfg, run_root, ["wild"], None)
    assert json.loads((run_root / cfg.name / "config.json").read_text()) == base


def test_isar_base_loss_stage_option(tmp_path):
    """ISAR's base_loss (docs/learning.md) is checked when the config is read, and the
    paper's isar_ppo_one stage builds isar_one's ISARConfig with the PPO base."""
    from geonav.experiments.stages import _algo_cfg

    base = {"scenes": {"A": {"synthetic": "residential"}}, "tasks": {"t": {"scene": "A"}}}

    def stage(**opts):
        return parse_config({**base, "stages": {"s": {"mode": "train", "tasks": "t",
                                                      "algo": "isar", **opts}}})

    assert stage(base_loss="ppo", ppo_epochs=2).stages["s"].options["base_loss"] == "ppo"
    with pytest.raises(ConfigError, match=r"base_loss = 'sac': use one of \('a3c', 'ppo'\)"):
        stage(base_loss="sac")
    with pytest.raises(ConfigError, match="base_loss is an ISAR option"):
        parse_config({**base, "stages": {"s": {"mode": "train", "tasks": "t", "algo": "a3c",
                                               "base_loss": "ppo"}}})
    with pytest.raises(ConfigError, match="implemented for mode 'train'"):
        parse_config({**base, "stages": {"s": {"mode": "meta-train", "tasks": "t",
                                               "algo": "isar", "base_loss": "ppo"}}})
    paper = load_config(Path(__file__).resolve().parent.parent / "configs" / "paper.toml")
    assert paper.stages_for(["isar-ppo"])
    cfgs = {}
    for key in ("isar_one", "isar_ppo_one"):
        st = paper.stages[key]
        cfg, net, rest = _algo_cfg({"algo": st.algo, "options": {**st.options,
                                                                 "obs_size_px": 84},
                                    "episodes": st.episodes, "workers": st.workers,
                                    "seed": 0, "tasks": None})
        cfgs[key] = cfg
    assert cfgs["isar_ppo_one"].base_loss == "ppo" and cfgs["isar_one"].base_loss == "a3c"
    assert replace(cfgs["isar_ppo_one"], base_loss="a3c") == cfgs["isar_one"]


def _fake_unit(root: Path, stage: str, seed: int, success: list[int],
               evals: list[tuple[int, float]]) -> None:
    """A finished unit's files as the runner writes them (no training)."""
    out = root / "units" / stage / f"seed-{seed}"
    out.mkdir(parents=True)
    rows = [f"{i + 1},{s},{i * 0.01:.2f},10,10" for i, s in enumerate(success)]
    (out / "metrics.csv").write_text("episode,success,elapsed_s,length,shortest_path\n"
                                     + "\n".join(rows) + "\n")
    (out / "eval.csv").write_text("episode,greedy_sr\n"
                                  + "".join(f"{e},{sr}\n" for e, sr in evals))
    (out / "result.json").write_text(json.dumps(
        {"stage": stage, "seed": seed, "episodes": len(success), "eval": {}}))


def test_count_parents_compares_totals_by_both_rules(tmp_path):
    """With count_parents, e* of each method by both rules, their ratios, the verdicts and
    README's row count the episodes of the starting stages: a fine-tune that converges
    fast on its own episodes but needed 500 meta-episodes before loses to scratch."""
    import tomllib

    from geonav.experiments.report import write_report
    from geonav.experiments.table import comparison_row

    data = tomllib.loads(TINY.replace("EPISODES", "150"))  # budget: noise check only
    data["compare"][0]["count_parents"] = True
    cfg = parse_config(data, "tiny.toml")
    root = tmp_path / "tiny"
    every = [(e, 1.0) for e in range(50, 401, 50)]
    for seed in (0, 1):
        _fake_unit(root, "pre", seed, [1] * 500, [])
        _fake_unit(root, "transfer", seed, [1] * 300, every[:6])
        _fake_unit(root, "scratch", seed, [0] * 199 + [1] * 201,
                   [(e, 0.0 if e < 250 else 1.0) for e, _ in every])
    summary = write_report(cfg, root, ["pre", "transfer", "scratch"], {}, {}, {})
    comp = summary["comparisons"][0]
    tr, sc = comp["methods"]["transfer"], comp["methods"]["scratch"]
    assert tr["convergence"]["median"] + 500 == tr["convergence_incl_parents"]["median"]
    assert tr["eval_convergence"]["median"] == 50
    assert tr["eval_convergence_incl_parents"]["median"] == 550
    assert sc["eval_convergence_incl_parents"]["median"] == 250  # no starting stage
    # on its own episodes transfer is faster; in all, scratch is, and both verdicts say so
    assert tr["convergence"]["median"] < sc["convergence"]["median"]
    for key in ("verdict", "eval_verdict"):
        assert comp[key].startswith("effect shown: scratch converges in fewer episodes"), \
            comp[key]
    assert comp["ratio"] > 1 and comp["eval_ratio"] == pytest.approx(550 / 250)
    report = (root / "report.md").read_text()
    assert "| 50 [50-50] (incl. earlier stages: 550 [550-550]) |" in report.replace(
        "; IQM 50 (95% CI 50-50)", "")
    row = comparison_row(root, summary, comp, tmp_path)
    assert "(transfer 550-550 vs scratch 250-250)" in row and "not reproduced" in row


def test_report_shows_view_ablated_sr_and_tolerates_runs_without_it(tmp_path):
    """The view-ablated greedy SR (final, zero-shot, curves) where the runs have it; "n/a"
    for runs evaluated before it existed (no ablated_sr in eval.csv or result.json)."""
    import numpy as np
    import tomllib

    from geonav.experiments.report import read_eval_column, write_report

    cfg = parse_config(tomllib.loads(TINY.replace("EPISODES", "150")), "tiny.toml")
    root = tmp_path / "tiny"
    chance = {"random_walk_sr": 0.04, "blind_sr": 0.3, "mean_shortest_path": 5.0}
    for seed in (0, 1):
        _fake_unit(root, "pre", seed, [1] * 100, [])
        _fake_unit(root, "transfer", seed, [1] * 100, [(50, 0.5), (100, 0.8)])  # old files
        _fake_unit(root, "scratch", seed, [1] * 100, [])
        unit = root / "units"
        (unit / "scratch" / f"seed-{seed}" / "eval.csv").write_text(
            "episode,greedy_sr,ablated_sr\n50,0.5,0.2\n100,0.9,0.3\n")
        (unit / "scratch" / f"seed-{seed}" / "result.json").write_text(json.dumps(
            {"episodes": 100, "eval": {"greedy_sr": 0.9, "ablated_sr": 0.3 + 0.2 * seed,
                                       **chance}}))
        zero_shot = {"greedy_sr": 0.6, **({"ablated_sr": 0.1} if seed == 0 else {})}
        (unit / "transfer" / f"seed-{seed}" / "result.json").write_text(json.dumps(
            {"episodes": 100, "eval": {"greedy_sr": 0.8, "zero_shot": zero_shot}}))
        (unit / "pre" / f"seed-{seed}" / "result.json").write_text(json.dumps(
            {"episodes": 100, "eval": {"greedy_sr": 0.7, "ablated_sr": 0.2}}))
    assert np.isnan(read_eval_column(root / "units/transfer/seed-0/eval.csv",
                                     "ablated_sr")).all()
    summary = write_report(cfg, root, ["pre", "transfer", "scratch"], {}, {}, {})
    methods = summary["comparisons"][0]["methods"]
    assert methods["scratch"]["final_ablated_sr"] == pytest.approx(0.4)
    assert methods["scratch"]["zero_shot_ablated_sr"] is None
    assert methods["transfer"]["final_ablated_sr"] is None
    assert methods["transfer"]["zero_shot_ablated_sr"] == pytest.approx(0.1)
    assert summary["stages"]["pre"]["final_ablated_sr"] == pytest.approx(0.2)
    assert summary["stages"]["pre"]["zero_shot_ablated_sr"] == pytest.approx(0.1)
    report = (root / "report.md").read_text()
    assert "final view-ablated greedy SR" in report and "view-blind line" in report
    assert "best view-blind action bias (knows the target, ignores the view) 0.300" in report
    assert "state-blind" not in report
    rows: dict[str, str] = {}
    for line in report.splitlines():  # the comparison table's rows come before ## Stages'
        if line.startswith(("| scratch |", "| transfer |")):
            rows.setdefault(line.split(" | ")[0], line)
    assert "| 0.90 / n/a | n/a / n/a | 0.40 | n/a |" in rows["| scratch"]
    assert "| 0.80 / n/a | n/a / n/a | n/a | 0.60 [0.60-0.60] (view-ablated 0.10) |" \
        in rows["| transfer"]
    assert "view-ablated 0.20; random walk" in report
    assert "on the compared task: 0.60 [0.60-0.60], view-ablated 0.10 (that" in report
    assert (root / "curves-transfer-vs-scratch.png").stat().st_size > 10_000


def test_run_folder_is_read_where_it_is_after_a_copy_or_move(tmp_path):
    """result.json stores paths relative to the run folder; one written with absolute paths
    (before they were relative) is read from the folder's new place too. A copy is reported
    from the copy, and with the original gone, every seed still counts."""
    import shutil

    import tomllib

    from geonav.experiments.report import write_report
    from geonav.experiments.runner import read_result, write_result

    cfg = parse_config(tomllib.loads(TINY.replace("EPISODES", "150")), "tiny.toml")
    first = tmp_path / "first" / "tiny"
    for stage in ("pre", "transfer", "scratch"):
        for seed in (0, 1):
            _fake_unit(first, stage, seed, [1] * 100, [(50, 0.5), (100, 1.0)])
    unit = first / "units" / "scratch" / "seed-0"
    write_result(unit, {"episodes": 100, "eval": {}, "metrics": str(unit / "metrics.csv"),
                        "checkpoint": str(unit / "checkpoints" / "final.pt"),
                        "tasks": str(first / "tasks" / "B_target.json"),
                        "scene": "/elsewhere/scene"})
    stored = json.loads((unit / "result.json").read_text())
    assert stored["metrics"] == "units/scratch/seed-0/metrics.csv"
    assert stored["tasks"] == "tasks/B_target.json"
    assert stored["scene"] == "/elsewhere/scene"  # outside the run folder: kept as given
    old = first / "units" / "transfer" / "seed-1"  # as geonav wrote them before
    (old / "result.json").write_text(json.dumps(
        {"episodes": 100, "eval": {}, "metrics": str(old / "metrics.csv"),
         "checkpoint": str(old / "checkpoints" / "final.pt")}))

    moved = tmp_path / "second" / "tiny"
    shutil.copytree(first, moved)
    # the copy is read from the copy, even while the original is still there
    assert read_result(moved / "units/scratch/seed-0")["metrics"] == \
        str(moved / "units/scratch/seed-0/metrics.csv")
    assert read_result(moved / "units/transfer/seed-1")["checkpoint"] == \
        str(moved / "units/transfer/seed-1/checkpoints/final.pt")
    (moved / "units/transfer/seed-1/metrics.csv").write_text(
        "episode,success,elapsed_s,length,shortest_path\n1,1,0.1,5,4\n")
    shutil.rmtree(tmp_path / "first")
    summary = write_report(cfg, moved, ["pre", "transfer", "scratch"], {}, {}, {})
    assert summary["unreadable"] == {}
    runs = summary["comparisons"][0]["methods"]["transfer"]["runs"]
    assert [r["episodes"] for r in runs] == [100, 1]  # seed 1 from the copy's own file
    assert "| transfer | train | a3c | B_target | 150 | 2/2 |" in \
        (moved / "report.md").read_text()


def test_report_leaves_out_unreadable_units_and_says_so(tmp_path):
    """A corrupt metrics row mid-file, or a finished unit whose metrics are gone, is listed
    under 'Unreadable units' (and makes `experiment report` exit 1) instead of a traceback
    or a silent '1/2 seeds done'."""
    import tomllib

    from geonav.experiments.report import write_report

    cfg = parse_config(tomllib.loads(TINY.replace("EPISODES", "150")), "tiny.toml")
    root = tmp_path / "tiny"
    for stage in ("pre", "transfer", "scratch"):
        for seed in (0, 1):
            _fake_unit(root, stage, seed, [1] * 100, [(50, 0.5), (100, 1.0)])
    bad = root / "units" / "scratch" / "seed-1" / "metrics.csv"
    lines = bad.read_text().splitlines()
    lines[10] = "10,x,0.1,10,10"
    bad.write_text("\n".join(lines) + "\n")
    (root / "units" / "transfer" / "seed-0" / "metrics.csv").unlink()
    summary = write_report(cfg, root, ["pre", "transfer", "scratch"], {}, {}, {})
    assert sorted(summary["unreadable"]) == ["scratch/seed-1", "transfer/seed-0"]
    assert "line 11 cannot be read" in summary["unreadable"]["scratch/seed-1"]
    assert "does not exist" in summary["unreadable"]["transfer/seed-0"]
    report = (root / "report.md").read_text()
    assert "## Unreadable units" in report
    assert "| scratch | train | a3c | B_target | 150 | 1/2 (1 unreadable) |" in report


def test_ingestion_warns_only_about_what_the_run_flies(tmp_path):
    """configs/tiny.toml flies 45 m tasks at 75 m on 1 m/px scenes: no warning about the
    paper's 15 m views or 150 m tasks at 300 m (every tiny run printed four); a config
    that does fly 15 m views on that imagery is warned about them, and only them."""
    import warnings

    import tomllib

    from geonav.errors import GeonavWarning
    from geonav.experiments.runner import coverage_needs, prepare_inputs
    from geonav.tiles.ingest import CoverageNeeds, check_coverage

    raw = tomllib.loads((Path(__file__).resolve().parent.parent / "configs" /
                         "tiny.toml").read_text())
    cfg = parse_config(raw, "tiny.toml")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", GeonavWarning)
        scenes, _ = prepare_inputs(cfg, tmp_path / "tiny")
    assert not [w for w in seen if issubclass(w.category, GeonavWarning)], \
        [str(w.message) for w in seen]
    from geonav.scene import Scene

    scene = Scene.open(scenes["A"])
    assert len(check_coverage(scene)) == 2  # the paper's protocol, when nothing says more
    low = coverage_needs(replace(cfg, tasks={"A_meta": replace(
        cfg.tasks["A_meta"], kind="scene", alts_m=(75.0, 15.0))}), "A", ["A_meta"])
    assert low == CoverageNeeds(views=((75.0, 32, 90.0), (15.0, 32, 90.0)), tasks=())
    [blur] = check_coverage(scene, low)
    assert "that 32 px views at 15 m need" in blur
    assert coverage_needs(cfg, "B", ["A_meta"]) == CoverageNeeds((), ())  # not on B


def test_init_alt_m_starts_from_one_level_of_a_curriculum(tmp_path):
    """``init_alt_m`` picks that level's final policy of the parent curriculum unit, and
    is refused in one line when the parent is no curriculum or lacks the level."""
    from geonav.experiments.runner import _payload
    from geonav.experiments.units import Unit

    base = {"scenes": {"A": {"synthetic": "residential"}},
            "tasks": {"t": {"scene": "A", "kind": "scene"}},
            "stages": {"cur": {"mode": "curriculum", "tasks": "t"},
                       "pre": {"mode": "train", "tasks": "t"},
                       "s": {"mode": "train", "tasks": "t", "init": "cur",
                             "init_alt_m": 45.0}}}
    cfg = parse_config(base)
    with pytest.raises(ConfigError, match=r"init_alt_m = 30 is not a level of curriculum"):
        parse_config({**base, "stages": {**base["stages"], "s": {
            **base["stages"]["s"], "init_alt_m": 30.0}}})
    with pytest.raises(ConfigError, match="init_alt_m needs init = a curriculum stage"):
        parse_config({**base, "stages": {**base["stages"], "s": {
            **base["stages"]["s"], "init": "pre"}}})
    unit = tmp_path / "units" / "cur" / "seed-0"
    levels = [(i, alt) for i, alt in enumerate((75.0, 45.0, 15.0))]
    for i, alt in levels:
        ck = unit / f"stage_{i}_{alt:g}m" / "checkpoints" / "final.pt"
        ck.parent.mkdir(parents=True)
        ck.write_bytes(b"")
    (unit / "checkpoints").mkdir()
    (unit / "curriculum.json").write_text(json.dumps(
        {"stages": [{"alt_m": alt, "checkpoint": "elsewhere"} for _, alt in levels]}))
    done = {Unit("cur", 0): {"checkpoint": str(unit / "checkpoints" / "final.pt")}}
    p = _payload(cfg, tmp_path, Unit("s", 0), {"A": "scenes/A"}, {"t": "tasks/t.json"}, done)
    assert p["init_checkpoint"] == str(unit / "stage_1_45m" / "checkpoints" / "final.pt")
    assert p["init_alt_m"] == 45.0
    (unit / "curriculum.json").write_text(json.dumps({"stages": [{"alt_m": 75.0}]}))
    with pytest.raises(ConfigError, match="no finished 45 m level"):
        _payload(cfg, tmp_path, Unit("s", 0), {"A": "scenes/A"}, {"t": "tasks/t.json"}, done)


def test_fly_auto_skips_a_flight_stage_the_selected_parts_do_not_train(tmp_path, capsys):
    from geonav.experiments.cli import _should_fly

    cfg = load_config(Path(__file__).resolve().parent.parent / "configs" / "paper.toml")
    assert cfg.flight["stage"] == "transfer_B"
    assert _should_fly(cfg, "auto", None)
    assert _should_fly(cfg, "auto", ["transfer"])
    assert not _should_fly(cfg, "auto", ["curriculum-mask"])
    assert "flight: skipped" in capsys.readouterr().out
    assert _should_fly(cfg, "yes", ["curriculum-mask"])
    assert not _should_fly(cfg, "no", None)
    assert not _should_fly(replace(cfg, flight={}), "auto", None)


def test_init_reset_draws_the_heads_again_and_refuses_unknown_values(tmp_path):
    """A train stage's init_reset: after the init weights load, 'critic' draws the value
    head again, 'heads' both heads; the trunk stays the init's."""
    import torch

    from geonav.experiments.stages import _init_reset, check_stage
    from geonav.policy.config import NetConfig
    from geonav.policy.model import ActorCritic

    torch.manual_seed(0)
    init = ActorCritic(NetConfig(encoder="random"))
    for which, changed in (("none", set()), ("critic", {"critic"}),
                           ("heads", {"critic", "actor"})):
        m = ActorCritic(NetConfig(encoder="random"))
        m.load_state_dict(init.state_dict())
        m.reset_heads(which)
        diff = {k.split(".")[0] for k, v in m.state_dict().items()
                if not torch.equal(v, init.state_dict()[k]) and k.endswith("weight")}
        assert diff == changed, which
    p = {"stage": "s", "mode": "train", "algo": "isar", "episodes": 10, "workers": 1,
         "seed": 0, "options": {"init_reset": "all"}}
    with pytest.raises(ConfigError, match=r"\[stages.s\] init_reset = 'all'"):
        check_stage(p, 32)
    check_stage({**p, "options": {"init_reset": "critic"}}, 32)
    assert _init_reset(p, {}) == "none"
    base = {"scenes": {"A": {"synthetic": "residential"}}, "tasks": {"t": {"scene": "A"}},
            "stages": {"s": {"mode": "train", "tasks": "t", "init_reset": "heads"}}}
    with pytest.raises(ConfigError, match=r"\[stages.s\] init_reset = 'heads' .* no init"):
        parse_config(base)
