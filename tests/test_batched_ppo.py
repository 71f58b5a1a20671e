"""Batched PPO: the recurrent recompute matches acting, and it learns the tiny task."""

import torch
from batched_helpers import greedy_sr, random_sr

from geonav.policy.batched.ppo import BatchedPPOTrainer, PPOConfig
from geonav.policy.testing import tiny_env_factory, tiny_net


def test_recompute_of_minibatch_sequences_matches_acting():
    """Whole-sequence minibatches over slots, recomputed from their stored start states
    across episode ends, give the acting log-probabilities and values (ratio = 1)."""
    factory = tiny_env_factory(max_steps=5)
    t = BatchedPPOTrainer(factory, tiny_net("random", 32, size=16), PPOConfig(episodes=10),
                          batch=6, tensorboard=False)
    t._setup()
    t.collect(7, keep_policy=True)  # slots are now mid-episode with non-zero states
    ro, finals = t.collect(12, keep_policy=True)
    assert finals and ro.starts[1:].any()  # episodes end and begin inside the rollout
    slots = torch.tensor([4, 1, 3])
    logits, values = t.recompute(ro, slots)
    logp = torch.log_softmax(logits, -1).gather(-1, ro.actions[:, slots, None])[..., 0]
    torch.testing.assert_close(logp, ro.logprobs[:, slots], atol=1e-5, rtol=0)
    torch.testing.assert_close(values, ro.values[:, slots], atol=1e-5, rtol=0)


def test_learns_tiny_task():
    factory = tiny_env_factory(cells=4, max_steps=7)
    env = factory()
    t = BatchedPPOTrainer(factory, tiny_net("random", 32),
                          PPOConfig(episodes=1000, lr=3e-3, seed=0), batch=16,
                          tensorboard=False)
    res = t.train()
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert sr >= rnd + 0.4, (sr, rnd)
