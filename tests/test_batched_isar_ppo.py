"""ISAR with PPO as its base loss (ISARConfig.base_loss = 'ppo', docs/learning.md): the
first pass against the A3C base, the later passes' replay of the window, learning,
refusals. The window gradient against functional_call is in test_batched_core.py, the
surrogate's gradient in test_policy_losses.py."""

from dataclasses import replace

import pytest
import torch
from batched_helpers import float64, greedy_sr, random_sr

from geonav.errors import ConfigError
from geonav.policy.batched.isar import BatchedISARTrainer
from geonav.policy.engine import build_meta_trainer, resolve
from geonav.policy.isar import ISARTrainer
from geonav.policy.meta_config import ISARConfig, MetaConfig
from geonav.policy.testing import tiny_env_factory, tiny_net

NET = tiny_net("random", 32, size=16)
CFG = ISARConfig(episodes=50, n_steps=3, k_segments=3, alpha=0.5, lr=1e-2, seed=4,
                 base_loss="ppo", max_grad_norm=0.0)


def _trainer(cfg, batch=4, net=NET):
    # 6-step episodes in 9-step windows: every slot's episode ends inside the first window
    factory = tiny_env_factory(cells=4, max_steps=6)
    return float64(BatchedISARTrainer(factory, net, cfg, batch=batch, tensorboard=False))


def _first_update(t, no_step=False):
    """The gradients of each pass of the trainer's first update, and its finished episodes."""
    grads = []
    t._setup()
    t.on_gradients = lambda gs: grads.append([g.clone() for g in gs])
    if no_step:
        t.optimizer.step = lambda *a, **k: None
    finals, _ = t.update()
    return grads, finals


def _max_diff(a, b):
    return max(float((x - y).abs().max()) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("batch", [1, 4])
def test_one_epoch_first_order_is_the_a3c_base(batch):
    """On the first pass the acting theta_k is the one differentiated: the ratio is 1 and
    the first-order window gradient is the A3C base's. In second order the surrogate's
    Hessian adds A grad log pi grad log pi^T to the inner step's Jacobian, so they differ."""
    for order in (False, True):
        cfg = replace(CFG, ppo_epochs=1, second_order=order)
        (ppo,), _ = _first_update(_trainer(cfg, batch))
        (a3c,), _ = _first_update(_trainer(replace(cfg, base_loss="a3c"), batch))
        if not order:
            for x, y in zip(ppo, a3c, strict=True):
                torch.testing.assert_close(x, y, atol=1e-12, rtol=1e-12)
        else:
            assert _max_diff(ppo, a3c) > 1e-8


@pytest.mark.parametrize("second_order,net", [(True, NET), (False, NET),
                                               (True, tiny_net("cnn", size=16)),
                                               (False, tiny_net("cnn", size=16))],
                         ids=["second-random", "first-random", "second-cnn", "first-cnn"])
def test_later_passes_replay_the_window(second_order, net):
    """With phi held still, every pass after the first recomputes the window (views,
    episode starts and ends, the slots reset to phi, inner updates) to the same gradient;
    with Adam stepping, the ratio leaves 1 and the passes' gradients differ. With the
    trainable CNN the replay encodes each slot's views and target under its adapted
    convolutions again, as the acting pass did."""
    cfg = replace(CFG, ppo_epochs=3, second_order=second_order)
    grads, finals = _first_update(_trainer(cfg, net=net), no_step=True)
    assert len(grads) == 3 and len(finals) >= 4  # episodes ended inside the window
    for g in grads[1:]:
        for x, y in zip(g, grads[0], strict=True):
            torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-10)
    moving, _ = _first_update(_trainer(cfg, net=net))
    for x, y in zip(moving[0], grads[0], strict=True):  # the first pass is the same
        torch.testing.assert_close(x, y, atol=1e-12, rtol=1e-12)
    assert _max_diff(moving[1], moving[0]) > 1e-6 and _max_diff(moving[2], moving[1]) > 1e-6


def test_refusals():
    with pytest.raises(ConfigError, match="base_loss must be one of"):
        ISARConfig(base_loss="sac")
    with pytest.raises(ConfigError, match="ppo_epochs"):
        ISARConfig(ppo_epochs=0)
    with pytest.raises(ConfigError, match="clip_coef"):
        ISARConfig(clip_coef=1.5)
    factory = tiny_env_factory()
    with pytest.raises(ConfigError, match="batched engine only"):
        ISARTrainer(factory, NET, CFG, tensorboard=False)
    with pytest.raises(ConfigError, match="batched engine only"):
        resolve("isar", "async", NET, CFG)
    with pytest.raises(ConfigError, match="meta-training with ISAR's base_loss = 'ppo'"):
        build_meta_trainer("isar", "batched", factory, NET, CFG, MetaConfig(episodes=2))
    assert resolve("isar", "batched", NET, CFG).cls is BatchedISARTrainer


@pytest.mark.slow
def test_learns_tiny_task():
    """Greedy success from every start beyond random (the setting of the A3C base's test
    in test_batched_isar.py, with the PPO base and its default 4 epochs)."""
    factory = tiny_env_factory(cells=4, max_steps=7)
    env = factory()
    cfg = ISARConfig(episodes=1500, lr=1e-3, alpha=1e-2, adam_eps=1e-5, amsgrad=False,
                     second_order=False, seed=3, base_loss="ppo")
    t = BatchedISARTrainer(factory, tiny_net("random", 32), cfg, batch=16, tensorboard=False)
    res = t.train()
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert sr >= rnd + 0.3, (sr, rnd)
