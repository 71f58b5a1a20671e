"""Smoke tests of ``geonav train`` / ``geonav eval`` through geonav.policy.cli."""

from __future__ import annotations

import argparse
import json

import pytest

from geonav.policy import cli
from geonav.testing import textured_scene, tiny_taskset


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    scene = textured_scene(size_m=300.0)
    scene.save(root / "scene")
    tiny_taskset(scene, max_steps=10).save(root / "tasks.json")
    return root / "scene", root / "tasks.json"


def _parse(argv):
    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(argv)


def test_train_resume_and_eval(scene_files, tmp_path, capsys):
    scene, tasks = scene_files
    run = tmp_path / "run"
    base = ["train", "--algo", "a3c", "--scene", str(scene), "--tasks", str(tasks),
            "--altitude", "75", "--workers", "0", "--out", str(run), "--obs-size", "32",
            "--encoder", "random", "--no-progress"]
    args = _parse(base + ["--episodes", "3", "--seed", "1"])
    assert args.handler(args) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["a3c"]["episodes"] == 3 and config["net"]["encoder"] == "random"
    assert config["env"]["obs_size_px"] == 32
    for name in ("metrics.csv", "learning_curve.png", "checkpoints/final.pt",
                 "checkpoints/latest.pt"):
        assert (run / name).is_file(), name

    # an eval.csv from before the view-ablated columns: the resumed run appends in its columns
    import csv

    with open(run / "eval.csv", newline="") as f:
        old_rows = list(csv.DictReader(f))
    assert old_rows and "ablated_sr" in old_rows[0]
    old_fields = [k for k in old_rows[0] if not k.startswith("ablated_")]
    with open(run / "eval.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=old_fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(old_rows)
    args = _parse(base + ["--episodes", "5", "--resume", str(run / "checkpoints/latest.pt")])
    assert args.handler(args) == 0
    assert len((run / "metrics.csv").read_text().splitlines()) == 1 + 5
    with open(run / "eval.csv", newline="") as f:
        resumed = list(csv.DictReader(f))
    assert list(resumed[-1]) == old_fields and float(resumed[-1]["eval_s"]) >= 0.0

    out = tmp_path / "eval.json"
    args = _parse(["eval", str(run / "checkpoints/final.pt"), "--scene", str(scene),
                   "--tasks", str(tasks), "--max-starts", "4", "--json", str(out),
                   "--no-progress"])
    capsys.readouterr()
    assert args.handler(args) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["starts"] == 4
    for mode in ("greedy", "sampled", "ablated"):
        assert 0.0 <= summary[mode]["sr"] <= 1.0 and 0.0 <= summary[mode]["spl"] <= 1.0
    assert 0.0 < summary["random_walk_sr"] < 1.0 and "random walk" in captured.err
    assert "view-ablated (current view replaced by another cell's): SR" in captured.err
    assert "best view-blind (knows the target, ignores the view)" in captured.err
    per = json.loads(out.read_text())["per_episode"]
    assert len(per["greedy"]) == 4 and len(per["sampled"]) == 4 and len(per["ablated"]) == 4
    # every training run ends with a greedy + sampled evaluation row in eval.csv
    rows = (run / "eval.csv").read_text().splitlines()
    assert rows[0].startswith("episode,env_steps") and rows[-1].startswith("5,")


def test_eval_prints_strict_json_without_successes(scene_files, tmp_path, capsys,
                                                  monkeypatch):
    """A policy that never succeeds has no length ratio: null in the JSON, not NaN."""
    import math

    from geonav.policy import evaluation

    scene, tasks = scene_files
    run = tmp_path / "run"
    args = _parse(["train", "--scene", str(scene), "--tasks", str(tasks), "--out", str(run),
                   "--obs-size", "32", "--encoder", "random", "--no-progress",
                   "--episodes", "2", "--batch", "2"])
    assert args.handler(args) == 0
    real = evaluation.evaluate_both

    def never(*a, **kw):  # the real evaluation, as a policy without successes reports it
        res = real(*a, **kw)
        res["row"]["greedy_length_ratio"] = math.nan
        return res

    monkeypatch.setattr(evaluation, "evaluate_both", never)
    out = tmp_path / "eval.json"
    args = _parse(["eval", str(run / "checkpoints/final.pt"), "--scene", str(scene),
                   "--tasks", str(tasks), "--max-starts", "3", "--json", str(out)])
    capsys.readouterr()
    assert args.handler(args) == 0

    def strict(text):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in JSON"))

    assert strict(capsys.readouterr().out.strip().splitlines()[-1])["greedy"][
        "length_ratio"] is None
    assert strict(out.read_text())["greedy"]["length_ratio"] is None


def test_bad_input_is_one_clear_error(scene_files, tmp_path, capsys):
    scene, tasks = scene_files
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    code = cli.main(["eval", str(bad), "--scene", str(scene), "--tasks", str(tasks)])
    assert code == 2 and "corrupt" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _parse(["train", "--scene", "s", "--tasks", "t", "--out", "o", "--encoder", "vgg"])
    toml = tmp_path / "c.toml"
    toml.write_text("[a3c]\nlearning_rate = 0.1\n")
    code = cli.main(["train", "--scene", str(scene), "--tasks", str(tasks), "--out",
                     str(tmp_path / "r"), "--config", str(toml)])
    assert code == 2 and "learning_rate" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_step_budget_running_env_steps_and_tensorboard(scene_files, tmp_path, capsys):
    """Issue 15: --total-steps beside --episodes, a running env_steps column, and
    --tensorboard DIR under SB3's tag names."""
    import csv

    pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    scene, tasks = scene_files
    run, tb = tmp_path / "run", tmp_path / "tb"
    args = _parse(["train", "--algo", "a3c", "--engine", "async", "--scene", str(scene),
                   "--tasks", str(tasks), "--altitude", "75", "--workers", "0", "--out",
                   str(run), "--obs-size", "32", "--encoder", "random", "--no-progress",
                   "--episodes", "1000", "--total-steps", "60", "--tensorboard", str(tb)])
    assert args.handler(args) == 0
    rows = list(csv.DictReader(open(run / "metrics.csv")))
    steps = [int(r["env_steps"]) for r in rows]
    lengths = [int(r["length"]) for r in rows]
    assert steps == [sum(lengths[:i + 1]) for i in range(len(lengths))]  # a running total
    assert steps[-1] >= 60 and steps[-2] < 60 and len(rows) < 1000  # stopped by the budget
    assert "trained" in capsys.readouterr().out
    acc = EventAccumulator(str(next(tb.rglob("events.out.tfevents*")).parent))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    assert "rollout/success_rate" in tags and "rollout/ep_len_mean" in tags
    assert max(e.step for e in acc.Scalars("rollout/ep_len_mean")) <= steps[-1]


def test_a_refused_train_leaves_no_tensorboard_run(scene_files, tmp_path):
    """Issue 34: the event file is made when training starts, in SB3's run sub-folder; a
    train refused before that (here a missing --resume checkpoint) leaves none."""
    pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed")
    from geonav.errors import GeonavError

    scene, tasks = scene_files
    tb = tmp_path / "tb"
    args = _parse(["train", "--algo", "ppo", "--scene", str(scene), "--tasks", str(tasks),
                   "--out", str(tmp_path / "run"), "--obs-size", "32", "--encoder", "random",
                   "--no-progress", "--episodes", "4", "--tensorboard", str(tb),
                   "--resume", str(tmp_path / "missing.pt")])
    with pytest.raises((GeonavError, OSError)):
        args.handler(args)
    assert not list(tb.rglob("events.out.tfevents*"))
    args = _parse(["train", "--algo", "ppo", "--scene", str(scene), "--tasks", str(tasks),
                   "--out", str(tmp_path / "run2"), "--obs-size", "32", "--encoder", "random",
                   "--no-progress", "--episodes", "4", "--tensorboard", str(tb)])
    assert args.handler(args) == 0
    assert [p.parent.name for p in tb.rglob("events.out.tfevents*")] == ["PPO_1"]


def test_progress_is_lines_when_not_a_terminal(scene_files, tmp_path, capsys, monkeypatch):
    """Issue 15: a redirected run prints progress lines (no carriage returns)."""
    monkeypatch.setenv("GEONAV_PROGRESS_S", "0")
    scene, tasks = scene_files
    args = _parse(["train", "--algo", "a3c", "--engine", "async", "--scene", str(scene),
                   "--tasks", str(tasks), "--altitude", "75", "--workers", "0", "--out",
                   str(tmp_path / "run"), "--obs-size", "32", "--encoder", "random",
                   "--episodes", "3"])
    assert args.handler(args) == 0
    err = capsys.readouterr().err
    assert "training: episode 3/3" in err and "\r" not in err
    assert "evaluation at episode 3: greedy SR" in err


def test_a_step_budget_is_the_budget_and_progress_counts_steps(scene_files, tmp_path, capsys,
                                                               monkeypatch):
    """Issue 34: --total-steps without --episodes is not capped by the default 1000
    episodes, and progress counts env steps against it ('episode 83/1000' before)."""
    import csv

    from geonav.policy.config import NO_EPISODE_LIMIT

    monkeypatch.setenv("GEONAV_PROGRESS_S", "0")
    scene, tasks = scene_files
    run = tmp_path / "run"
    # at most 5 steps an episode: 6,000 steps need 1,200+ episodes
    args = _parse(["train", "--algo", "a3c", "--scene", str(scene), "--tasks", str(tasks),
                   "--altitude", "75", "--workers", "0", "--out", str(run), "--obs-size", "32",
                   "--encoder", "random", "--max-steps", "5", "--total-steps", "6000"])
    assert args.handler(args) == 0
    rows = list(csv.DictReader(open(run / "metrics.csv")))
    assert len(rows) > 1000 and int(rows[-1]["env_steps"]) >= 6000
    assert json.loads((run / "config.json").read_text())["a3c"]["episodes"] == NO_EPISODE_LIMIT
    err = capsys.readouterr().err
    assert f"training into {run}: env step 0/6000 (episode 0)" in err
    assert "training: env step " in err and "/6000, episode " in err and "/1000" not in err
    # an episode budget given beside it is kept, and shown beside the steps
    args = _parse(["train", "--scene", str(scene), "--tasks", str(tasks), "--out", "o",
                   "--episodes", "7", "--total-steps", "6000"])
    assert cli.resolve_train_configs(args)[1].episodes == 7
    toml = tmp_path / "c.toml"
    toml.write_text("[a3c]\nepisodes = 9\ntotal_steps = 50\n")
    args = _parse(["train", "--scene", str(scene), "--tasks", str(tasks), "--out", "o",
                   "--config", str(toml)])
    assert cli.resolve_train_configs(args)[1].episodes == 9
    toml.write_text("[a3c]\ntotal_steps = 50\n")
    assert cli.resolve_train_configs(args)[1].episodes == NO_EPISODE_LIMIT


def test_no_progress_silences_progress_only(scene_files, tmp_path, capsys, monkeypatch):
    """--no-progress: no bar and no periodic lines, but the start line (where the run goes),
    the evaluations and the closing result line (with the checkpoint) are still there."""
    monkeypatch.setenv("GEONAV_PROGRESS_S", "0")
    scene, tasks = scene_files
    run = tmp_path / "run"
    args = _parse(["train", "--algo", "isar", "--scene", str(scene), "--tasks", str(tasks),
                   "--altitude", "75", "--workers", "0", "--out", str(run), "--obs-size", "32",
                   "--encoder", "random", "--episodes", "4", "--no-progress"])
    assert args.handler(args) == 0
    out, err = capsys.readouterr()
    assert err.splitlines()[0] == f"training into {run}: episode 0/4"
    assert "training: episode" not in err  # no periodic progress
    assert "evaluation at episode 4: greedy SR" in err
    assert out.startswith("trained 4 episodes") and \
        f"checkpoint {run / 'checkpoints' / 'final.pt'}" in out


def test_eval_all_starts_script_evaluates_every_start_once(scene_files, tmp_path, capsys):
    """scripts/eval_all_starts.py: each finished unit's final policy from every start of its
    task set (the runner's evaluations sample ``eval_starts``); kept per unit, not redone."""
    import importlib.util
    from pathlib import Path

    from geonav.env import GeoNavEnv
    from geonav.scene import Scene
    from geonav.tasks import TaskSet

    spec = importlib.util.spec_from_file_location(
        "eval_all_starts", Path(__file__).resolve().parents[1] / "scripts" / "eval_all_starts.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)

    scene, tasks = scene_files
    unit = tmp_path / "run" / "units" / "s" / "seed-0"
    args = _parse(["train", "--algo", "a3c", "--scene", str(scene), "--tasks", str(tasks),
                   "--workers", "0", "--out", str(unit), "--obs-size", "32", "--encoder",
                   "random", "--no-progress", "--episodes", "2", "--seed", "0"])
    assert args.handler(args) == 0
    (unit / "result.json").write_text(json.dumps({
        "checkpoint": str(unit / "checkpoints" / "final.pt"), "scene": str(scene),
        "tasks": str(tasks)}))
    capsys.readouterr()
    assert script.main([str(tmp_path / "run"), "--stages", "s", "--jobs", "1"]) == 0
    row = json.loads((unit / script.OUT).read_text())
    env = GeoNavEnv(Scene.open(scene), TaskSet.load(tasks))
    every = sum(len(env.start_cells(i)) for i in range(len(env.task_maps)))
    assert row["starts"] == every > 4
    assert 0.0 <= row["greedy_sr"] <= 1.0 and 0.0 < row["random_walk_sr"] < 1.0
    out = capsys.readouterr().out
    assert f"| s | {every} | {row['greedy_sr']:.2f} (seeds 0) |" in out
    stamp = (unit / script.OUT).stat().st_mtime_ns
    assert script.main([str(tmp_path / "run"), "--stages", "s", "--jobs", "1"]) == 0
    assert (unit / script.OUT).stat().st_mtime_ns == stamp
    with pytest.raises(SystemExit, match="no finished units"):
        script.main([str(tmp_path / "run"), "--stages", "nope"])
    cur = tmp_path / "run" / "units" / "c" / "seed-0"
    cur.mkdir(parents=True)
    (cur / "result.json").write_text(json.dumps({"mode": "curriculum"}))
    with pytest.raises(SystemExit, match="is a curriculum"):
        script.main([str(tmp_path / "run"), "--stages", "c"])
