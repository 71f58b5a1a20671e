"""The engine option through the CLI: batched by default, async on request, PPO, device."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np
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


@pytest.mark.parametrize("algo", ["isar", "savn"])
def test_isar_and_savn_with_the_trainable_cnn_run_batched(scene_files, tmp_path, algo):
    run = tmp_path / algo
    argv = _base(scene_files, run, algo)
    argv[argv.index("--encoder") + 1] = "cnn"
    assert _run(argv) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["engine"]["name"] == "batched" and config["engine"]["batch"] == 4
    assert len((run / "metrics.csv").read_text().splitlines()) == 1 + 6


def test_meta_isar_with_the_trainable_cnn_runs_batched():
    """Per-task copies of the trainable CNN (meta-training's ISAR and A3C bases) run on the
    batched engine (run-stacked phi^i, tests/test_batched_meta.py), and so does the SAVN
    base with E > 1: no fallback."""
    from geonav.policy.engine import build_meta_trainer
    from geonav.policy.meta_config import ISARConfig, MetaConfig, SAVNConfig
    from geonav.policy.testing import tiny_env_factory, tiny_net

    t = build_meta_trainer("isar", "batched", tiny_env_factory(), tiny_net("cnn"),
                           ISARConfig(), MetaConfig(episodes=1, workers=0),
                           tensorboard=False)
    assert t.engine_choice.engine == "batched"
    t = build_meta_trainer("savn", "batched", tiny_env_factory(), tiny_net("cnn"),
                           SAVNConfig(), MetaConfig(episodes=2, workers=0,
                                                    episodes_per_task=2),
                           tensorboard=False)
    assert t.engine_choice.engine == "batched"


def test_no_combination_falls_back_to_the_async_engine(caplog):
    """The last gaps are closed: ISAR without the partial-window flush (train and
    meta-train) and the previous-altitude view input of A3C and PPO resolve to the batched
    engine, without a warning; the async A3C worker, which has no extra input, refuses it."""
    from geonav.errors import ConfigError
    from geonav.policy.batched.isar import BatchedISARTrainer
    from geonav.policy.batched.meta import BatchedMetaISAR
    from geonav.policy.batched.ppo import BatchedPPOTrainer
    from geonav.policy.batched.trainer import BatchedA3CTrainer
    from geonav.policy.engine import build_meta_trainer, resolve
    from geonav.policy.meta_config import ISARConfig, MetaConfig
    from geonav.policy.testing import tiny_env_factory, tiny_net

    no_flush = ISARConfig(flush_partial_window=False)
    for algo, cfg, prev, cls in (("isar", no_flush, False, BatchedISARTrainer),
                                 ("isar", no_flush, True, BatchedISARTrainer),
                                 ("a3c", None, True, BatchedA3CTrainer),
                                 ("ppo", None, True, BatchedPPOTrainer)):
        choice = resolve(algo, "batched", None, cfg, prev_view=prev)
        assert (choice.cls, choice.engine, choice.reason) == (cls, "batched", None)
    t = build_meta_trainer("isar", "batched", tiny_env_factory(), tiny_net(),
                           replace(no_flush, lr_warmup=10), MetaConfig(episodes=1, workers=0),
                           tensorboard=False)
    assert isinstance(t, BatchedMetaISAR) and t.engine_choice.reason is None
    assert not [r for r in caplog.records if "engine 'async'" in r.getMessage()]
    with pytest.raises(ConfigError, match="batched engine only"):
        resolve("a3c", "async", None, None, prev_view=True)


def test_resume_from_an_earlier_checkpoint_drops_the_later_rows(scene_files, tmp_path):
    """metrics.csv and eval.csv keep no row logged after the resumed checkpoint, so the
    running env_steps column counts each episode once."""
    from geonav.policy.callbacks import read_metrics

    run, toml = tmp_path / "r", tmp_path / "c.toml"
    toml.write_text("[a3c]\nkeep_checkpoints = true\ncheckpoint_every = 4\neval_every = 4\n")
    argv = _base(scene_files, run, "a3c") + ["--config", str(toml)]
    argv[argv.index("--episodes") + 1] = "8"
    assert _run(argv) == 0
    assert _run(argv + ["--resume", str(run / "checkpoints" / "episode_4.pt")]) == 0
    rows = read_metrics(run / "metrics.csv")
    assert [int(r["episode"]) for r in rows] == list(range(1, 9))
    steps = [int(r["env_steps"]) for r in rows]
    assert steps == list(np.cumsum([int(r["length"]) for r in rows]))
    assert [int(r["episode"]) for r in read_metrics(run / "eval.csv")] == [4, 8]


def test_resume_across_engines(scene_files, tmp_path):
    """A batched checkpoint resumes on the single-process async engine and back (each
    engine starts its own random streams from the other's checkpoint)."""
    run = tmp_path / "r"
    assert _run(_base(scene_files, run, "a3c")) == 0
    latest = str(run / "checkpoints" / "latest.pt")
    for episodes, engine in (("8", ["--engine", "async", "--workers", "0"]), ("10", [])):
        argv = _base(scene_files, run, "a3c") + engine + ["--resume", latest]
        argv[argv.index("--episodes") + 1] = episodes
        assert _run(argv) == 0
    assert len((run / "metrics.csv").read_text().splitlines()) == 1 + 10
