"""A3C: learning on a tiny task, 2 worker processes, run-folder outputs, callbacks."""

from __future__ import annotations

import csv

import pytest
import torch

from geonav.errors import ConfigError
from geonav.policy.a3c import A3CTrainer, WorkerFailed, train_a3c
from geonav.policy.callbacks import Callback
from geonav.policy.config import A3CConfig
from geonav.policy.encoders import build_frozen_encoder
from geonav.policy.evaluation import RandomAgent, eval_starts, evaluate
from geonav.policy.testing import tiny_env_factory, tiny_net


def test_deterministic_a3c_beats_random_on_tiny_task():
    factory = tiny_env_factory(cells=4, max_steps=10)
    env = factory()
    starts = eval_starts(env, 40, seed=1)
    random_sr = evaluate(RandomAgent(seed=1), env, starts=starts).success_rate
    res = train_a3c(factory, tiny_net(), A3CConfig(episodes=150, workers=0, lr=1e-3, seed=0))
    assert res.episodes == 150 and len(res.records) == 150
    frozen = build_frozen_encoder(res.model.cfg)
    learned = evaluate(res.model, env, frozen=frozen, starts=starts, greedy=False, seed=1)
    assert random_sr < 0.45
    assert learned.success_rate >= 0.75
    assert learned.success_rate >= random_sr + 0.35
    assert learned.spl > 0.5


def test_deterministic_mode_is_reproducible():
    factory = tiny_env_factory()
    cfg = A3CConfig(episodes=6, workers=0, seed=3)
    a = train_a3c(factory, tiny_net(), cfg)
    b = train_a3c(factory, tiny_net(), cfg)
    assert [r["return"] for r in a.records] == [r["return"] for r in b.records]
    for pa, pb in zip(a.model.parameters(), b.model.parameters(), strict=True):
        assert torch.equal(pa, pb)


def test_two_workers_train_the_shared_model(tmp_path):
    factory = tiny_env_factory()
    trainer = A3CTrainer(factory, tiny_net(), A3CConfig(episodes=12, workers=2, seed=0,
                                                        checkpoint_every=5), out_dir=tmp_path,
                         mp_context="fork")
    before = [p.detach().clone() for p in trainer.model.parameters()]
    res = trainer.train()
    assert res.episodes == 12
    assert {r["worker"] for r in res.records} == {0, 1}
    assert sorted(r["episode"] for r in res.records) == list(range(1, 13))
    changed = [not torch.equal(a, b) for a, b in zip(before, res.model.parameters(), strict=True)]
    assert all(changed)
    step = next(iter(trainer.optimizer.state.values()))["step"]
    assert step.item() >= 12  # at least one shared Adam step per episode
    with open(tmp_path / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 12 and {"return", "length", "success", "spl", "collisions",
                                "task"} <= set(rows[0])
    assert (tmp_path / "checkpoints" / "final.pt").is_file()
    assert (tmp_path / "learning_curve.png").stat().st_size > 1000
    assert (tmp_path / "config.json").is_file()


def test_callbacks_see_every_episode_and_can_stop():
    seen = []

    class StopAt(Callback):
        def on_episode(self, record):
            seen.append(record["episode"])
            return len(seen) < 4

    res = train_a3c(tiny_env_factory(), tiny_net(), A3CConfig(episodes=50, workers=0),
                    callbacks=[StopAt()])
    assert seen == [1, 2, 3, 4] and res.episodes == 4


def test_refuses_to_overwrite_a_run(tmp_path):
    factory = tiny_env_factory()
    train_a3c(factory, tiny_net(), A3CConfig(episodes=2, workers=0), out_dir=tmp_path)
    before = (tmp_path / "metrics.csv").read_bytes()
    with pytest.raises(ConfigError, match="already holds a run"):
        train_a3c(factory, tiny_net(), A3CConfig(episodes=2, workers=0), out_dir=tmp_path)
    assert (tmp_path / "metrics.csv").read_bytes() == before


def test_network_must_match_env():
    with pytest.raises(ConfigError, match="px"):
        A3CTrainer(tiny_env_factory(obs_size_px=32), tiny_net(obs_size_px=64))


@pytest.mark.slow
def test_two_spawned_workers():
    # 'spawn' re-imports torch in every worker (several seconds), hence the marker.
    trainer = A3CTrainer(tiny_env_factory(), tiny_net(), A3CConfig(episodes=6, workers=2),
                         mp_context="spawn")
    before = trainer.model.actor.weight.detach().clone()
    res = trainer.train()
    assert res.episodes == 6 and {r["worker"] for r in res.records} == {0, 1}
    assert not torch.equal(before, res.model.actor.weight)


def test_a_failing_worker_is_reported():
    trainer = A3CTrainer(tiny_env_factory(), tiny_net(), A3CConfig(episodes=4, workers=1),
                         mp_context="fork")
    trainer.env_factory = _broken_factory
    with pytest.raises(WorkerFailed, match="no scene here"):
        trainer.train()


def _broken_factory():
    raise RuntimeError("no scene here")


def test_learner_reads_the_image_on_the_tiny_task():
    """Issue 10: the trained policy's first-step action probabilities differ across start
    cells (an image-blind policy has the same ones everywhere) and its greedy success from
    every start is well above the task's exact random-walk success."""
    import functools

    from geonav.camera import Camera
    from geonav.difficulty import env_difficulty
    from geonav.env import GeoNavEnv
    from geonav.policy.agent import obs_inputs
    from geonav.policy.evaluation import evaluate_both
    from geonav.policy.testing import _scene
    from geonav.testing import tiny_taskset

    # The target in the middle of a 5 x 5 lattice: no directional bias helps (the best
    # state-blind SR equals the random walk's, 0.33), so only the image can.
    scene = _scene(0)
    ts = tiny_taskset(scene, alt_m=75.0, cells=5, max_steps=12, target=(2, 2))
    factory = functools.partial(GeoNavEnv, scene, ts, camera=Camera(32, 90.0))
    env = factory()
    res = train_a3c(factory, tiny_net(), A3CConfig(episodes=300, workers=0, lr=1e-3, seed=0,
                                                   eval_every=0))
    frozen = build_frozen_encoder(res.model.cfg)
    probs = []
    for cell in env.unwrapped.start_cells(0):
        obs, info = env.reset(options={"task": 0, "start_cell": cell})
        view, target = obs_inputs(obs, info, frozen)
        with torch.no_grad():
            logits, _, _ = res.model(view[None, None], target[None], res.model.initial_state())
        probs.append(torch.softmax(logits[0, 0], -1))
    spread = torch.stack(probs).std(0).max().item()
    out = evaluate_both(res.model, env, frozen=frozen, max_starts=None)
    chance = env_difficulty(env)
    assert chance["blind_sr"] < 0.4
    assert spread > 0.05, spread
    assert out["row"]["greedy_sr"] >= chance["blind_sr"] + 0.4, (out["row"], chance)
