"""PolicyRunner (deployment) and evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from geonav.errors import CheckpointError
from geonav.policy.a3c import train_a3c
from geonav.policy.agent import Agent
from geonav.policy.checkpoint import load_checkpoint
from geonav.policy.config import A3CConfig
from geonav.policy.evaluation import RandomAgent, eval_starts, evaluate, spl
from geonav.policy.inference import PolicyRunner
from geonav.policy.testing import tiny_env_factory, tiny_net


@pytest.fixture(scope="module", params=["random", "cnn"])
def run(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(f"run-{request.param}")
    factory = tiny_env_factory(max_steps=12)
    train_a3c(factory, tiny_net(request.param), A3CConfig(episodes=8, workers=0, lr=1e-3),
              out_dir=out)
    return out / "checkpoints" / "final.pt", factory


def test_runner_acts_like_greedy_evaluation(run):
    path, factory = run
    env = factory()
    ck = load_checkpoint(path)
    starts = eval_starts(env, 6, seed=2)
    res = evaluate(ck.build_model(), env, frozen=ck.build_encoder(), starts=starts, greedy=True)
    runner = PolicyRunner.from_checkpoint(path)
    for rec, (ti, cell) in zip(res.episodes, starts, strict=True):
        runner.reset()
        obs, info = env.reset(options={"task": ti, "start_cell": cell})
        actions = []
        done = False
        while not done:
            a = runner.act(obs["image"], obs["target"])
            actions.append(a)
            obs, _, term, trunc, info = env.step(a)
            done = term or trunc
        assert actions == rec["actions"]


def test_runner_meta_and_input_checks(run):
    path, _ = run
    runner = PolicyRunner.from_checkpoint(path)
    for key in ("obs_size_px", "alt_m", "step_m", "fov_deg"):
        assert key in runner.meta
    assert runner.action_meanings == ["forward", "right", "left", "backward"]
    img = np.zeros((32, 32, 3), np.uint8)
    assert runner.act(img, img) in range(4)
    with pytest.raises(CheckpointError, match=r"\(32, 32, 3\)"):
        runner.act(np.zeros((84, 84, 3), np.uint8), img)


def test_runner_keeps_state_between_calls(run):
    path, factory = run
    runner = PolicyRunner.from_checkpoint(path)
    env = factory()
    obs, _ = env.reset(seed=0)
    runner.act(obs["image"], obs["target"])
    h1 = runner.agent.state[0].clone()
    runner.act(obs["image"], obs["target"])
    assert not np.allclose(h1.numpy(), runner.agent.state[0].numpy())
    runner.reset()
    assert float(runner.agent.state[0].abs().sum()) == 0.0


def test_eval_starts_are_fixed_and_seeded():
    env = tiny_env_factory()()
    assert eval_starts(env, 10, seed=4) == eval_starts(env, 10, seed=4)
    assert eval_starts(env, 10, seed=4) != eval_starts(env, 10, seed=5)
    assert all(cell in env.unwrapped.start_cells(ti) for ti, cell in eval_starts(env, 30))


def test_eval_metrics_and_modes(run):
    path, factory = run
    env = factory()
    ck = load_checkpoint(path)
    model, frozen = ck.build_model(), ck.build_encoder()
    sampled = [evaluate(model, env, frozen=frozen, episodes_per_task=8, greedy=False, seed=3)
               for _ in range(2)]
    assert sampled[0].episodes == sampled[1].episodes  # seeded
    r = sampled[0]
    assert r.success_rate == pytest.approx(np.mean([e["success"] for e in r.episodes]))
    assert r.spl == pytest.approx(np.mean([e["spl"] for e in r.episodes]))
    assert r.mean_length == pytest.approx(np.mean([e["length"] for e in r.episodes]))
    rnd = evaluate(RandomAgent(seed=0), env, episodes_per_task=8)
    assert 0.0 <= rnd.success_rate <= 1.0 and rnd.mean_collisions >= 0


def test_spl():
    assert spl(True, 3, 3) == 1.0
    assert spl(True, 3, 6) == 0.5
    assert spl(False, 3, 3) == 0.0


def test_agent_cache_hits():
    from geonav.policy.encoders import build_frozen_encoder
    from geonav.policy.model import ActorCritic

    net = tiny_net("random")
    frozen = build_frozen_encoder(net)
    env = tiny_env_factory()()
    evaluate(Agent(ActorCritic(net), frozen), env, episodes_per_task=5)
    assert frozen.misses <= len(env.unwrapped.start_cells(0)) + 1  # each view encoded once
    assert frozen.hits > frozen.misses
