"""Batched SAVN: B = 1 equals the reference worker's episode meta-gradient; it learns."""

import pytest
import torch
from batched_helpers import (
    assert_grads_close,
    first_update_grads,
    greedy_sr,
    kl_teacher_spec,
    random_sr,
)

from geonav.policy.batched.savn import BatchedSAVNTrainer
from geonav.policy.meta_config import SAVNConfig
from geonav.policy.savn import SAVNTrainer
from geonav.policy.testing import tiny_env_factory, tiny_net


@pytest.mark.parametrize("second_order,encoder", [(True, "random"), (False, "random"),
                                                  (True, "cnn"), (False, "cnn")])
def test_b1_episode_meta_gradient_equals_reference(second_order, encoder):
    """The trainable CNN adapts in the inner steps too (per-slot dense weight changes)."""
    factory = tiny_env_factory(cells=5, max_steps=12)
    net = tiny_net(encoder, 32, size=16)
    cfg = SAVNConfig(episodes=1, workers=0, k_steps=3, inner_steps=2, inner_lr=0.5, seed=4,
                     second_order=second_order)
    ref = SAVNTrainer(factory, net, cfg, tensorboard=False)
    bat = BatchedSAVNTrainer(factory, net, cfg, batch=1, tensorboard=False)
    ref_grads, got, rec, _, finals = first_update_grads(ref, bat)
    assert rec["inner_updates"] == 2  # the learned loss adapted theta twice
    assert [f["length"] for f in finals] == [rec["length"]]
    names = [n for n, _ in ref.model.named_parameters()] + \
        [f"ll.{n}" for n, _ in ref.aux["interaction_loss"].named_parameters()]
    assert_grads_close(names, ref_grads, got, 1e-5, 1e-4)
    if second_order:  # Lambda learns through the second-order path only
        assert float(got[-1].abs().sum()) > 0


@pytest.mark.slow
def test_learns_tiny_task():
    factory = tiny_env_factory(cells=4, max_steps=7)
    env = factory()
    cfg = SAVNConfig(episodes=1500, lr=1e-3, adam_eps=1e-5, amsgrad=False, seed=0)
    t = BatchedSAVNTrainer(factory, tiny_net("random", 32), cfg, batch=16, tensorboard=False)
    res = t.train()
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert sr >= rnd + 0.3, (sr, rnd)


@pytest.mark.slow
def test_learns_tiny_task_with_the_trainable_cnn():
    """The CNN trained end to end, adapted per slot in the inner steps."""
    factory = tiny_env_factory(cells=4, max_steps=7)
    env = factory()
    cfg = SAVNConfig(episodes=1000, lr=1e-3, adam_eps=1e-5, amsgrad=False, seed=0,
                     eval_every=0)
    t = BatchedSAVNTrainer(factory, tiny_net("cnn", 32), cfg, batch=16, tensorboard=False)
    res = t.train()
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert sr >= rnd + 0.3, (sr, rnd)


def test_b1_with_kl_teacher_equals_reference(tmp_path):
    """The curriculum's KL prior in the learned loss and the meta-loss (option A)."""
    net = tiny_net("random", 32, size=16)
    spec = kl_teacher_spec(net, tmp_path)
    factory = tiny_env_factory(cells=5, max_steps=12)
    cfg = SAVNConfig(episodes=1, workers=0, k_steps=3, inner_steps=2, inner_lr=0.5, seed=4)
    ref = SAVNTrainer(factory, net, cfg, teacher=spec, tensorboard=False)
    bat = BatchedSAVNTrainer(factory, net, cfg, teacher=spec, batch=1, tensorboard=False)
    ref_grads, got, rec, _, finals = first_update_grads(ref, bat)
    assert rec["kl_weight"] == 1.0 and bat.record(finals[0], {})["kl_weight"] == 1.0
    names = [n for n, _ in ref.model.named_parameters()] + \
        [f"ll.{n}" for n, _ in ref.aux["interaction_loss"].named_parameters()]
    assert_grads_close(names, ref_grads, got, 1e-5, 1e-4)


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_b1_truncation_bootstrap_equals_reference(encoder):
    """``bootstrap_on_truncation``: an episode cut by the step cap bootstraps its meta-loss
    with V(s_T) under the last theta (the reference's update; without it, another one)."""
    from dataclasses import replace

    from geonav.policy.config import LossConfig

    factory = tiny_env_factory(cells=5, max_steps=7)
    net = tiny_net(encoder, 32, size=16)
    cfg = SAVNConfig(episodes=1, workers=0, k_steps=3, inner_steps=2, inner_lr=0.5, seed=4,
                     loss=LossConfig(bootstrap_on_truncation=True))
    ref = SAVNTrainer(factory, net, cfg, tensorboard=False)
    bat = BatchedSAVNTrainer(factory, net, cfg, batch=1, tensorboard=False)
    ref_grads, got, rec, _, _ = first_update_grads(ref, bat)
    assert not rec["success"] and rec["length"] == 7  # truncated, after two inner steps
    names = [n for n, _ in ref.model.named_parameters()] + \
        [f"ll.{n}" for n, _ in ref.aux["interaction_loss"].named_parameters()]
    assert_grads_close(names, ref_grads, got, 1e-5, 1e-4)
    off = replace(cfg, loss=LossConfig())
    _, no_boot, _, _, _ = first_update_grads(SAVNTrainer(factory, net, off, tensorboard=False),
                                             BatchedSAVNTrainer(factory, net, off, batch=1,
                                                                tensorboard=False))
    assert max(float((a - b).abs().max()) for a, b in zip(got, no_boot, strict=True)) > 1e-5


@pytest.mark.parametrize("second_order", [True, False])
def test_b1_episode_with_previous_view_input_and_cnn_equals_reference(float64_default,
                                                                      second_order):
    """Option B with the trainable CNN: the previous-altitude views encoded under each
    slot's adapted weights, as the async worker does (float64, 1e-10)."""
    from dataclasses import replace

    from geonav.policy.teacher import PrevViewSpec

    net = replace(tiny_net("cnn", 20, size=16), prev_view_input=True)
    factory = tiny_env_factory(cells=5, max_steps=12, obs_size_px=20)
    spec = PrevViewSpec(tiny_env_factory(cells=5, max_steps=12, alt_m=90.0, obs_size_px=20),
                        90.0)
    cfg = SAVNConfig(episodes=1, workers=0, k_steps=3, inner_steps=2, inner_lr=0.5, seed=4,
                     second_order=second_order)
    ref = SAVNTrainer(factory, net, cfg, prev_view=spec, tensorboard=False)
    bat = BatchedSAVNTrainer(factory, net, cfg, prev_view=spec, batch=1, tensorboard=False)
    ref_grads, got, rec, _, _ = first_update_grads(ref, bat)
    assert rec["inner_updates"] == 2 and got[0].dtype == torch.float64
    names = [n for n, _ in ref.model.named_parameters()] + \
        [f"ll.{n}" for n, _ in ref.aux["interaction_loss"].named_parameters()]
    assert_grads_close(names, ref_grads, got, 1e-10, 1e-10)
    assert float(got[names.index("prev_embed.weight")].abs().max()) > 0
