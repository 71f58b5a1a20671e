"""Smoke tests of train --algo savn/isar, meta-train, curriculum, and the stage trainers."""

from __future__ import annotations

import argparse
import dataclasses
import json

import pytest

from geonav.policy import cli
from geonav.testing import textured_scene, tiny_taskset


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    scene = textured_scene(size_m=300.0)
    scene.save(root / "scene")
    ts = tiny_taskset(scene, max_steps=10)
    tasks = [dataclasses.replace(ts.tasks[0], name=f"t{i}", target_cell=c)
             for i, c in enumerate([(3, 3), (0, 0)])]
    dataclasses.replace(ts, tasks=tasks).save(root / "tasks.json")
    return root / "scene", root / "tasks.json"


def _run(argv):
    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.handler(args)


@pytest.mark.parametrize("algo", ["isar", "savn"])
def test_train_new_algos_and_resume(files, tmp_path, algo):
    scene, tasks = files
    run = tmp_path / "run"
    base = ["train", "--algo", algo, "--scene", str(scene), "--tasks", str(tasks),
            "--workers", "0", "--out", str(run), "--obs-size", "32", "--encoder", "random",
            "--no-progress", "--first-order"]
    assert _run(base + ["--episodes", "3"]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["algorithm"] == algo and config[algo]["second_order"] is False
    assert config["gradient_path"]["order"] == "first"
    assert _run(base + ["--episodes", "5", "--resume", str(run / "checkpoints/latest.pt")]) == 0
    assert len((run / "metrics.csv").read_text().splitlines()) == 1 + 5


def test_meta_train_and_curriculum_commands(files, tmp_path, capsys):
    scene, tasks = files
    common = ["--scene", str(scene), "--tasks", str(tasks), "--workers", "0",
              "--obs-size", "32", "--encoder", "random", "--no-progress"]
    meta = tmp_path / "meta"
    assert _run(["meta-train", "--algo", "savn", "--preset", "savn-aligned", "--episodes", "4",
                 "--batch-tasks", "2", "--out", str(meta), *common]) == 0
    config = json.loads((meta / "config.json").read_text())
    assert config["meta"]["batch_tasks"] == 2 and config["base"]["k_steps"] == 5
    cur = tmp_path / "cur"
    argv = ["curriculum", "--init", str(meta / "checkpoints/final.pt"), "--levels", "45,15",
            "--stage-episodes", "3", "--out", str(cur), "--window", "50", *common[:6]]
    assert _run(argv + ["--no-progress"]) == 0
    state = json.loads((cur / "curriculum.json").read_text())
    assert [s["alt_m"] for s in state["stages"]] == [45.0, 15.0]
    assert state["stages"][1]["teacher"] == state["stages"][0]["checkpoint"]
    assert (cur / "checkpoints" / "final.pt").is_file()
    assert _run(argv + ["--no-progress"]) == 0  # everything done: resumes to the end


@pytest.mark.parametrize("mode,algo", [("train", "isar"), ("meta-train", "isar"),
                                       ("curriculum", "savn")])
def test_stage_trainers(files, tmp_path, mode, algo):
    from geonav.experiments.stages import TRAINERS
    from geonav.policy.checkpoint import load_checkpoint
    from geonav.policy.cli import EnvFactory

    scene, tasks = files
    p = dict(mode=mode, algo=algo, episodes=3, workers=0, seed=0, scene=str(scene),
             tasks=str(tasks), init_checkpoint=None, out_dir=str(tmp_path / "u"),
             options={"encoder": "random", "obs_size_px": 32, "hidden_size": 32,
                      "lstm_size": 32}, convergence={"window": 50})
    if mode == "curriculum":
        p["options"] = {"levels_m": [45.0], "teacher": "none", "k_steps": 4}
        first = dict(p, mode="train", algo="isar", out_dir=str(tmp_path / "init"),
                     options={"encoder": "random", "obs_size_px": 32})
        _, _, ck = TRAINERS[("train", "isar")](
            first, EnvFactory(str(scene), str(tasks), obs_size_px=32), [], None)
        p["init_checkpoint"] = ck
    factory = EnvFactory(str(scene), str(tasks), obs_size_px=32)
    model, episodes, ckpt = TRAINERS[(mode, algo)](p, factory, [], None)
    assert episodes == 3 and load_checkpoint(ckpt).episodes == 3
    if mode != "curriculum":  # resume from latest.pt with a larger budget
        p["episodes"] = 4
        _, episodes, _ = TRAINERS[(mode, algo)](p, factory, [],
                                                str(tmp_path / "u/checkpoints/latest.pt"))
        assert episodes == 4


def test_train_isar_base_loss_option(files, tmp_path, capsys):
    """`geonav train --algo isar` exposes ISARConfig's base_loss, clip_coef and ppo_epochs
    (help from the fields' docstrings); the async engine refuses the PPO base."""
    from geonav.errors import ConfigError

    with pytest.raises(SystemExit):
        _run(["train", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--base-loss {a3c,ppo}" in out and "clipped surrogate" in out
    assert "--ppo-epochs" in out and "--clip-coef" in out
    scene, tasks = files
    run = tmp_path / "run"
    base = ["train", "--algo", "isar", "--scene", str(scene), "--tasks", str(tasks),
            "--out", str(run), "--obs-size", "32", "--encoder", "random", "--no-progress",
            "--base-loss", "ppo", "--ppo-epochs", "2", "--clip-coef", "0.1"]
    assert _run(base + ["--episodes", "3", "--batch", "2"]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["isar"]["base_loss"] == "ppo" and config["isar"]["ppo_epochs"] == 2
    assert config["isar"]["clip_coef"] == 0.1 and config["engine"]["name"] == "batched"
    with pytest.raises(ConfigError, match="batched engine only"):
        _run(base + ["--episodes", "3", "--engine", "async", "--out", str(tmp_path / "a")])


def test_curriculum_teacher_variants_from_the_command_line(files, tmp_path):
    """--teacher-mask/--teacher-schedule/--teacher-agree reach the stage's teacher (its
    config.json says so); on the async engine they are refused with one clear line."""
    from geonav.errors import ConfigError

    scene, tasks = files
    common = ["--scene", str(scene), "--tasks", str(tasks), "--obs-size", "32",
              "--encoder", "random", "--no-progress", "--levels", "45,15",
              "--stage-episodes", "3", "--window", "50", "--teacher-mask", "feasible",
              "--teacher-schedule", "agree", "--teacher-agree", "0.8"]
    cur = tmp_path / "cur"
    assert _run(["curriculum", "--out", str(cur), "--engine", "batched", *common]) == 0
    config = json.loads((cur / "stage_1_15m" / "config.json").read_text())
    assert config["teacher"]["mask"] == "feasible" and config["teacher"]["agree"] == 0.8
    assert config["teacher"]["schedule"] == "agree"
    with pytest.raises(ConfigError, match="need the batched engine"):
        _run(["curriculum", "--out", str(tmp_path / "a"), "--engine", "async",
              "--workers", "0", *common])
