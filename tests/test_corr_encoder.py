"""The correlation encoder ('corr'): the maths, one feature path for every consumer (the
reference env and agent, the batched tables, the lock-step evaluation, the flight runner),
the reference update at B = 1, and what it is for: a policy trained on one scene that
navigates on another."""

import numpy as np
import pytest
import torch
from batched_helpers import assert_grads_close, first_update_grads, greedy_sr, random_sr

from geonav.errors import ConfigError
from geonav.policy.a3c import A3CTrainer
from geonav.policy.agent import Agent, obs_inputs
from geonav.policy.batched.ppo import BatchedPPOTrainer, PPOConfig
from geonav.policy.batched.trainer import BatchedA3CTrainer
from geonav.policy.config import A3CConfig, NetConfig
from geonav.policy.encoders import build_frozen_encoder, feature_dim, view_correlation
from geonav.policy.evaluation import evaluate, evaluate_lockstep
from geonav.policy.inference import PolicyRunner
from geonav.policy.model import ActorCritic
from geonav.policy.testing import tiny_env_factory, tiny_net
from geonav.vecenv import LatticeVecEnv


def corr_net(radius=6, size=32):
    return NetConfig(encoder="corr", obs_size_px=32, corr_radius=radius, hidden_size=size,
                     lstm_size=size)


def test_correlation_peaks_at_the_shift_and_is_normalised():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(3, 20, 20, generator=g)
    b = torch.roll(a, shifts=(2, -3), dims=(1, 2))  # b[y, x] = a[y - 2, x + 3]
    c = view_correlation(a.flatten(1), b.flatten(1), 20, 5).reshape(3, 11, 11)
    for m in range(3):
        i, j = divmod(int(c[m].argmax()), 11)
        assert (i - 5, j - 5) == (2, -3)
    assert float(c[:, 7, 2].min()) > 0.7  # about 1 at the shift (the roll wraps the edges)
    other = torch.randn(3, 400, generator=g)
    assert float(view_correlation(a.flatten(1), other, 20, 5).abs().max()) < 0.35
    auto = view_correlation(a.flatten(1), a.flatten(1), 20, 5).reshape(3, 11, 11)
    torch.testing.assert_close(auto[:, 5, 5], torch.ones(3), atol=1e-5, rtol=0)
    assert feature_dim(NetConfig(encoder="corr", corr_radius=5)) == 121


def test_config_refusals():
    with pytest.raises(ConfigError, match="corr_radius"):
        NetConfig(encoder="corr", obs_size_px=32, corr_radius=16)
    with pytest.raises(ConfigError, match="prev_view_input"):
        NetConfig(encoder="corr", prev_view_input=True)
    NetConfig(encoder="random", obs_size_px=16)  # the radius only binds the corr encoder
    frozen = build_frozen_encoder(corr_net())
    with pytest.raises(ValueError, match="target"):
        frozen.features(np.zeros((32, 32, 3), np.uint8))


def test_every_consumer_sees_the_same_features():
    """The env + agent path (async trainers), the batched table, the lock-step evaluation
    and the flight runner agree: a view's features are its correlation with the episode's
    target, the target's its autocorrelation."""
    factory = tiny_env_factory(cells=5, max_steps=12)
    env = factory()
    net = corr_net()
    frozen = build_frozen_encoder(net)
    venv = LatticeVecEnv(env.unwrapped, 1)
    table = venv.feature_table(frozen)
    assert table.shape == (25, 169)
    ti = 0
    tgt_row = int(venv.target_view[ti])
    for cell in env.unwrapped.start_cells(ti):
        obs, info = env.reset(options={"start_cell": cell})
        v, t = obs_inputs(obs, info, frozen)
        torch.testing.assert_close(v, table[venv.view_of(ti, cell)], atol=1e-5, rtol=0)
        torch.testing.assert_close(t, table[tgt_row], atol=1e-5, rtol=0)
    assert float(table[tgt_row].max()) == pytest.approx(1.0, abs=1e-4)
    torch.manual_seed(0)
    model = ActorCritic(net)
    starts = [(0, c) for c in env.unwrapped.start_cells(0)]
    a = evaluate(model, env, frozen=frozen, starts=starts)
    b = evaluate_lockstep(model, env, starts, frozen=frozen)
    assert a.success_rate == b.success_rate and a.spl == pytest.approx(b.spl)
    runner = PolicyRunner(Agent(model, frozen), {"obs_size_px": 32})
    obs, _ = env.reset(options={"start_cell": starts[0][1]})
    runner.reset()
    x = model.features(obs_inputs(obs, None, frozen)[0])
    runner_act = runner.act(obs["image"], obs["target"])
    with torch.no_grad():
        logits, _, _ = model(x[None, None], obs_inputs(obs, None, frozen)[1][None],
                             model.initial_state(1))
    assert runner_act == int(logits[0, 0].argmax())


def test_b1_first_update_equals_reference_worker():
    factory = tiny_env_factory(cells=5, max_steps=12)
    net = corr_net(size=16)
    cfg = A3CConfig(episodes=1, workers=0, t_max=3, seed=4)
    ref = A3CTrainer(factory, net, cfg, tensorboard=False)
    bat = BatchedA3CTrainer(factory, net, cfg, batch=1, tensorboard=False)
    ref_grads, got, rec, _, _ = first_update_grads(ref, bat)
    assert rec["length"] > cfg.t_max
    names = [n for n, _ in ref.model.named_parameters()]
    assert_grads_close(names, ref_grads, got, 2e-6, 1e-5)


def corner_targets_factory(seed, targets, cells=5, max_steps=10):
    """A picklable factory of a multi-task env: one task per target on the same lattice."""
    import functools
    from dataclasses import replace

    from geonav.camera import Camera
    from geonav.env import GeoNavEnv
    from geonav.policy.testing import _scene
    from geonav.testing import tiny_taskset

    scene = _scene(seed)
    ts = tiny_taskset(scene, cells=cells, max_steps=max_steps)
    tasks = [replace(ts.tasks[0], name=f"t{k}", target_cell=tuple(t))
             for k, t in enumerate(targets)]
    return functools.partial(GeoNavEnv, scene, replace(ts, tasks=tasks),
                             camera=Camera(32, 90.0))


@pytest.mark.slow
def test_a_policy_trained_on_one_scene_navigates_another():
    """What the encoder is for (docs/learning.md §8): PPO trained on 20 targets of a 5 x 5
    lattice of one textured scene reaches the 5 other targets on a scene it never saw,
    greedily, from most starts, where the random CNN's features at the same budget do not
    carry over. (Each evaluation clears the encoder's cache: its keys are (task index,
    cell, altitude), which two different envs share.)"""
    import random as pyrandom

    cells = [(i, j) for i in range(5) for j in range(5)]
    pyrandom.Random(0).shuffle(cells)
    train = corner_targets_factory(0, cells[:20])
    other = corner_targets_factory(1, cells[20:])()
    rnd = random_sr(other)
    out = {}
    for enc in ("corr", "random"):
        net = corr_net() if enc == "corr" else tiny_net("random", 32, size=32)
        t = BatchedPPOTrainer(train, net, PPOConfig(episodes=3000, seed=0, lr=1e-3), batch=16,
                              tensorboard=False)
        res = t.train()
        srs = []
        for env in (train(), other):
            t.frozen.clear()
            srs.append(greedy_sr(res.model, t.frozen, env))
        out[enc] = tuple(srs)
    assert out["corr"][0] >= 0.9, (out, rnd)
    assert out["corr"][1] >= max(rnd + 0.4, 0.8), (out, rnd)
    assert out["corr"][1] > out["random"][1] + 0.2, (out, rnd)
