"""Batched PPO: the recurrent recompute matches acting, and it learns the tiny task; the
feed-forward network (NetConfig.recurrent=False) with single-step minibatches likewise."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from batched_helpers import greedy_sr, random_sr

from geonav.errors import ConfigError
from geonav.policy.batched.ppo import BatchedPPOTrainer, PPOConfig
from geonav.policy.testing import tiny_env_factory, tiny_net


@pytest.mark.parametrize("case", ["plain", "prev", "prev-cnn"])
def test_recompute_of_minibatch_sequences_matches_acting(case):
    """Whole-sequence minibatches over slots, recomputed from their stored start states
    across episode ends, give the acting log-probabilities and values (ratio = 1). prev:
    the previous-altitude view input (curriculum option B, as batched A3C feeds it: while
    acting and in the recompute), which moves the values from the zero-filled slot's."""
    from geonav.policy.teacher import PrevViewSpec

    px = 20 if case.endswith("cnn") else 32
    net = replace(tiny_net("cnn" if case.endswith("cnn") else "random", px, size=16),
                  prev_view_input=case != "plain")
    factory = tiny_env_factory(max_steps=5, obs_size_px=px)
    spec = PrevViewSpec(tiny_env_factory(max_steps=5, alt_m=90.0, obs_size_px=px), 90.0) \
        if case != "plain" else None
    rollouts = {}
    for prev in ([spec, None] if spec is not None else [None]):
        t = BatchedPPOTrainer(factory, net, PPOConfig(episodes=10), prev_view=prev, batch=6,
                              tensorboard=False)
        t._setup()
        t.collect(7, keep_policy=True)  # slots are now mid-episode with non-zero states
        ro, finals = t.collect(12, keep_policy=True)
        assert finals and ro.starts[1:].any()  # episodes end and begin inside the rollout
        slots = torch.tensor([4, 1, 3])
        logits, values = t.recompute(ro, slots)
        logp = torch.log_softmax(logits, -1).gather(-1, ro.actions[:, slots, None])[..., 0]
        torch.testing.assert_close(logp, ro.logprobs[:, slots], atol=1e-5, rtol=0)
        torch.testing.assert_close(values, ro.values[:, slots], atol=1e-5, rtol=0)
        rollouts[prev is None] = ro, t
    if spec is not None:
        (with_prev, t), (zero, _) = rollouts[False], rollouts[True]
        assert float((with_prev.values[0] - zero.values[0]).abs().max()) > 1e-6
        assert t.resolved_config()["teacher"] == {"kind": "input", "prev_alt_m": 90.0}


def test_learns_tiny_task():
    factory = tiny_env_factory(cells=4, max_steps=7)
    env = factory()
    t = BatchedPPOTrainer(factory, tiny_net("random", 32),
                          PPOConfig(episodes=1000, lr=3e-3, seed=0), batch=16,
                          tensorboard=False)
    res = t.train()
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert sr >= rnd + 0.4, (sr, rnd)


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_feed_forward_flat_minibatches_match_acting(encoder):
    """NetConfig.recurrent=False: the rollout seen as T x B single steps (flat_steps, PPO's
    minibatches of single steps) recomputes the acting log-probabilities and values, and
    the network has no LSTM and no previous-action input."""
    from geonav.policy.batched.ppo import flat_steps

    px = 20 if encoder == "cnn" else 32
    net = replace(tiny_net(encoder, px, size=16), recurrent=False)
    t = BatchedPPOTrainer(tiny_env_factory(max_steps=5, obs_size_px=px), net,
                          PPOConfig(episodes=10), batch=6, tensorboard=False)
    assert t.model.lstm is None and t.model.action_embed is None
    t._setup()
    t.collect(7, keep_policy=True)
    ro, finals = t.collect(12, keep_policy=True)
    assert finals
    returns, advantages = t.advantages(ro, ro.values)
    flat, fret, fadv = flat_steps(ro, returns, advantages)
    assert flat.view_idx.shape == (1, 72) and fret.shape == fadv.shape == (1, 72)
    cols = torch.tensor([0, 13, 40, 71])  # column s * T + t
    s, step = cols // 12, cols % 12
    logits, values = t.recompute(flat, cols)
    logp = torch.log_softmax(logits, -1).gather(-1, flat.actions[:, cols, None])[..., 0]
    torch.testing.assert_close(logp[0], ro.logprobs[step, s], atol=1e-5, rtol=0)
    torch.testing.assert_close(values[0], ro.values[step, s], atol=1e-5, rtol=0)
    torch.testing.assert_close(fadv[0, cols], advantages[step, s])


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_sequence_chunks_match_acting(encoder):
    """PPOConfig.seq_len: the recurrent rollout cut into chunks of L steps, each started
    from the state it was acted from (across episode ends inside and between chunks),
    recomputes the acting log-probabilities and values, chunk by chunk; an update runs."""
    from geonav.policy.batched.ppo import chunk_steps

    px = 20 if encoder == "cnn" else 32
    t = BatchedPPOTrainer(tiny_env_factory(max_steps=5, obs_size_px=px),
                          tiny_net(encoder, px, size=16),
                          PPOConfig(episodes=10, t_max=12, seq_len=4), batch=6,
                          tensorboard=False)
    t._setup()
    t.collect(7, keep_policy=True)  # slots mid-episode with non-zero states
    ro, finals = t.collect(12, keep_policy=True, keep_states=True)
    assert finals and ro.starts[1:].any()
    returns, advantages = t.advantages(ro, ro.values)
    ch, cret, cadv = chunk_steps(ro, returns, advantages, 4)
    assert ch.view_idx.shape == (4, 18) and cret.shape == cadv.shape == (4, 18)
    cols = torch.tensor([0, 4, 8, 17])  # column s * 3 + j: slot s's steps 4j .. 4j + 3
    s, j = cols // 3, cols % 3
    logits, values = t.recompute(ch, cols)
    logp = torch.log_softmax(logits, -1).gather(-1, ch.actions[:, cols, None])[..., 0]
    for k in range(len(cols)):
        steps = slice(4 * int(j[k]), 4 * int(j[k]) + 4)
        torch.testing.assert_close(logp[:, k], ro.logprobs[steps, s[k]], atol=1e-5, rtol=0)
        torch.testing.assert_close(values[:, k], ro.values[steps, s[k]], atol=1e-5, rtol=0)
        torch.testing.assert_close(cadv[:, cols[k]], advantages[steps, s[k]])
    assert int(j[1]) == 1 and bool(ro.step_states[0][4, 1].abs().sum() > 0)  # a carried state
    before = [p.detach().clone() for p in t.params_list]
    t.update()
    assert any(float((p.detach() - q).abs().max()) > 0 for p, q in zip(t.params_list, before,
                                                               strict=True))
    with pytest.raises(ConfigError, match="seq_len must be 0 or a divisor"):
        PPOConfig(t_max=12, seq_len=5)


def test_feed_forward_learns_tiny_task():
    """The feed-forward network learns the tiny task with single-step minibatches."""
    factory = tiny_env_factory(cells=4, max_steps=7)
    env = factory()
    net = replace(tiny_net("random", 32), recurrent=False)
    t = BatchedPPOTrainer(factory, net, PPOConfig(episodes=1000, lr=3e-3, seed=0,
                                                  minibatches=8), batch=16, tensorboard=False)
    res = t.train()
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert sr >= rnd + 0.4, (sr, rnd)


def test_separate_critic_keeps_the_heads_apart():
    """NetConfig.separate_critic: the FC layer is 2H wide, the value's gradient reaches
    only the critic's half and the policy's only the actor's; PPO's flat minibatches still
    recompute the acting values; a recurrent network refuses it."""
    from geonav.policy.batched.ppo import flat_steps

    net = replace(tiny_net("random", 32, size=16), recurrent=False, separate_critic=True)
    t = BatchedPPOTrainer(tiny_env_factory(max_steps=5), net, PPOConfig(episodes=10),
                          batch=6, tensorboard=False)
    h = net.hidden_size
    assert t.model.fc.weight.shape[0] == 2 * h and t.model.critic.weight.shape[1] == h
    t._setup()
    ro, finals = t.collect(12, keep_policy=True)
    returns, advantages = t.advantages(ro, ro.values)
    flat, _, _ = flat_steps(ro, returns, advantages)
    cols = torch.tensor([0, 13, 40, 71])
    logits, values = t.recompute(flat, cols)
    torch.testing.assert_close(values[0], ro.values[cols % 12, cols // 12], atol=1e-5, rtol=0)
    fc = t.model.fc.weight
    for out, half in ((values.sum(), slice(0, h)), (logits.sum(), slice(h, 2 * h))):
        (g,) = torch.autograd.grad(out, fc, retain_graph=True)
        assert float(g[half].abs().max()) == 0.0 and float(g.abs().max()) > 0
    with pytest.raises(ConfigError, match="separate_critic needs a feed-forward"):
        replace(net, recurrent=True)


def test_critic_warmup_moves_only_the_critic_head():
    """PPOConfig.critic_warmup: the first rollouts fit the critic head alone (its value
    loss falls), every other weight stays bit for bit; after them PPO updates everything."""
    factory = tiny_env_factory(cells=4, max_steps=7)
    t = BatchedPPOTrainer(factory, tiny_net("random", 32, size=16),
                          PPOConfig(episodes=10, seed=0, critic_warmup=3, lr=1e-2), batch=8,
                          tensorboard=False)
    t._setup()
    before = {n: p.detach().clone() for n, p in t.model.named_parameters()}
    ro, _ = t.collect(7, keep_policy=True)
    returns, _ = t.advantages(ro, ro.values)

    def value_loss():
        with torch.no_grad():
            return float((0.5 * (returns - t.recompute(ro)[1]).pow(2)).mean())

    start = value_loss()
    t.critic_update(ro, returns)
    assert value_loss() < start  # fitted on that rollout
    for _ in range(3):
        assert t.update()[1]["critic_warmup"]
    for n, p in t.model.named_parameters():
        same = torch.equal(p, before[n])
        assert same != n.startswith("critic."), n
    t.update()  # the fourth is a PPO update: the actor moves
    assert not torch.equal(t.model.actor.weight, before["actor.weight"])
    with pytest.raises(Exception, match="critic_warmup must be >= 0"):
        PPOConfig(critic_warmup=-1)


def test_default_bootstraps_at_truncation():
    """PPO's default (SB3's handling of timeouts): an episode cut by the step cap is
    bootstrapped with V of its last observation, a reached target with 0. The same rollout
    under ``bootstrap_on_truncation = false`` differs exactly at the truncated episodes'
    last steps, by gamma * V."""
    factory = tiny_env_factory(cells=4, max_steps=4)
    net = tiny_net("random", 32, size=16)
    cfg = PPOConfig(episodes=10, seed=1)
    assert cfg.loss.bootstrap_on_truncation and cfg.loss.tau == 0.95
    out = {}
    for on in (True, False):
        t = BatchedPPOTrainer(factory, net, replace(cfg, loss=replace(
            cfg.loss, bootstrap_on_truncation=on)), batch=8, tensorboard=False)
        t._setup()
        ro, _ = t.collect(12, keep_policy=True)
        out[on] = ro, t.advantages(ro, ro.values)[0]
    (ro, r_on), (ro_off, r_off) = out[True], out[False]
    torch.testing.assert_close(ro.values, ro_off.values)  # the same acting
    cut = ro.ends & (ro.rewards < 1.0)  # ended without reaching the target
    reached = ro.ends & (ro.rewards > 1.0)
    assert cut.any() and reached.any()
    assert ro_off.end_values is None and ro.end_values is not None
    assert (ro.end_values[~cut] == 0).all() and (ro.end_values[cut] != 0).all()
    diff = (r_on - r_off).numpy()
    np.testing.assert_allclose(diff[cut], cfg.loss.gamma * ro.end_values[cut], atol=1e-5)
    assert np.abs(diff[reached]).max() < 1e-6


@pytest.mark.parametrize("recurrent", [False, True])
def test_minibatch_steps_keeps_the_minibatch_size_as_slots_grow(recurrent):
    """PPOConfig.minibatch_steps: a rollout of t_max * batch steps is cut into minibatches
    of about that many steps, so 4x the slots take 4x the gradient steps per pass."""
    factory = tiny_env_factory(cells=4, max_steps=7)
    net = replace(tiny_net("random", 32), recurrent=recurrent)
    steps = {}
    for batch in (4, 16):
        t = BatchedPPOTrainer(factory, net, PPOConfig(episodes=10, seed=0, t_max=8, epochs=2,
                                                      minibatch_steps=16), batch=batch,
                              tensorboard=False)
        t._setup()
        calls = []
        step = t.step_optimizer
        t.step_optimizer = lambda loss, _s=step, _c=calls: (_c.append(1), _s(loss))[1]
        t.update()
        steps[batch] = len(calls)
    assert steps == {4: 2 * 2, 16: 2 * 8}  # 32 and 128 steps in minibatches of 16
    with pytest.raises(ConfigError, match="minibatch_steps must be >= 0"):
        PPOConfig(minibatch_steps=-1)
