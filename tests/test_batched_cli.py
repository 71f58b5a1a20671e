"""The engine option through the CLI: batched by default, async on request, PPO, device."""

from __future__ import annotations

import argparse
import json

import pytest
import torch

from geonav.policy import cli
from geonav.testing import textured_scene, tiny_taskset


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    scene = textured_scene(size_m=300.0)
    scene.save(root / "scene")
    tiny_taskset(scene, max_steps=10).save(root / "tasks.json")
    return root / "scene", root / "tasks.json"


def _run(argv):
    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.handler(args)


def _base(scene_files, out, algo):
    scene, tasks = scene_files
    return ["train", "--algo", algo, "--scene", str(scene), "--tasks", str(tasks),
            "--out", str(out), "--obs-size", "32", "--encoder", "random", "--no-progress",
            "--episodes", "6", "--batch", "4"]


@pytest.mark.parametrize("algo", ["a3c", "ppo", "isar", "savn"])
def test_train_runs_on_the_batched_engine_by_default(scene_files, tmp_path, algo):
    run = tmp_path / algo
    assert _run(_base(scene_files, run, algo)) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["engine"]["name"] == "batched" and config["engine"]["batch"] == 4
    assert len((run / "metrics.csv").read_text().splitlines()) == 1 + 6
    # resume continues the run on the engine from its checkpoint
    argv = _base(scene_files, run, algo)
    argv[argv.index("--episodes") + 1] = "9"
    assert _run(argv + ["--resume", str(run / "checkpoints" / "latest.pt")]) == 0
    assert len((run / "metrics.csv").read_text().splitlines()) == 1 + 9


def test_async_engine_and_refusals(scene_files, tmp_path):
    run = tmp_path / "async"
    assert _run(_base(scene_files, run, "a3c") + ["--engine", "async", "--workers", "0"]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["engine"] == {"name": "async", "asked": "async", "fallback_reason": None}
    from geonav.errors import ConfigError

    with pytest.raises(ConfigError, match="batched engine only"):
        _run(_base(scene_files, tmp_path / "p", "ppo") + ["--engine", "async"])
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no GPU"):
            _run(_base(scene_files, tmp_path / "c", "a3c") + ["--device", "cuda"])


def test_isar_with_the_trainable_cnn_falls_back_to_async(scene_files, tmp_path):
    run = tmp_path / "cnn"
    argv = _base(scene_files, run, "isar")
    argv[argv.index("--encoder") + 1] = "cnn"
    assert _run(argv + ["--workers", "0"]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["engine"]["name"] == "async" and "frozen encoder" in \
        config["engine"]["fallback_reason"]
