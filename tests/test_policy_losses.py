"""L_AC (ALGORITHMS.md 4.0): a hand-computed case, and the batched recompute fast path."""

from __future__ import annotations

import math

import pytest
import torch

from geonav.policy.a3c import Rollout, rollout_loss
from geonav.policy.config import A3CConfig, LossConfig, NetConfig
from geonav.policy.losses import actor_critic_loss, policy_value_terms, returns_and_advantages
from geonav.policy.model import ActorCritic

LN4 = math.log(4.0)


def test_hand_computed_episode_end():
    # Two steps, uniform policy (logits 0: log pi = -ln 4, H = ln 4), V = (0.5, 1.0),
    # rewards (-0.01, +5), the segment ends the episode: B = 0.
    # R1 = 5, R0 = -0.01 + 0.99 * 5 = 4.94
    # value = 1/2 (4.94 - 0.5)^2 + 1/2 (5 - 1)^2 = 9.8568 + 8 = 17.8568
    # delta1 = 5 + 0 - 1 = 4 -> gae1 = 4; delta0 = -0.01 + 0.99 * 1 - 0.5 = 0.48
    # gae0 = 0.48 + 0.99 * 4 = 4.44
    # policy = ln4 * 4.44 - 0.01 ln4 + ln4 * 4 - 0.01 ln4 = 8.42 ln4
    # total = policy + 0.5 * value
    logits = torch.zeros(2, 4, requires_grad=True)
    values = torch.tensor([0.5, 1.0], requires_grad=True)
    loss = actor_critic_loss(logits, values, [1, 3], [-0.01, 5.0], bootstrap=0.0)
    assert loss.value.item() == pytest.approx(17.8568, abs=1e-4)
    assert loss.policy.item() == pytest.approx(8.42 * LN4, abs=1e-4)
    assert loss.entropy.item() == pytest.approx(2 * LN4, abs=1e-6)
    assert loss.total.item() == pytest.approx(8.42 * LN4 + 0.5 * 17.8568, abs=1e-4)
    loss.total.backward()
    # dL/dV_t = 0.5 * (V_t - R_t): (0.5 - 4.94) / 2, (1 - 5) / 2
    assert values.grad.tolist() == pytest.approx([-2.22, -2.0], abs=1e-5)
    # d(-log pi(a) gae)/dlogits = -gae (onehot - p); the entropy term is flat at uniform.
    assert logits.grad[0].tolist() == pytest.approx([0.25 * 4.44, -0.75 * 4.44,
                                                     0.25 * 4.44, 0.25 * 4.44], abs=1e-5)


def test_hand_computed_bootstrap():
    # One step, not done, B = V(s_next) = 2: R = 1 + 0.99 * 2 = 2.98;
    # delta = 1 + 0.99 * 2 - 0.5 = 2.48 = gae; value = 1/2 (2.98 - 0.5)^2 = 3.0752.
    logits = torch.zeros(1, 4)
    loss = actor_critic_loss(logits, torch.tensor([0.5]), [0], [1.0], bootstrap=2.0,
                             cfg=LossConfig(beta=0.0))
    assert loss.value.item() == pytest.approx(3.0752, abs=1e-5)
    assert loss.policy.item() == pytest.approx(2.48 * LN4, abs=1e-5)


def test_gae_with_tau_below_one():
    r, adv = returns_and_advantages([0.0, 1.0], torch.tensor([0.2, 0.4]), 0.0, 0.5, 0.5)
    # R1 = 1, R0 = 0.5; delta1 = 1 - 0.4 = 0.6, delta0 = 0 + 0.5*0.4 - 0.2 = 0
    # gae0 = 0 + 0.25 * 0.6 = 0.15
    assert r.tolist() == pytest.approx([0.5, 1.0])
    assert adv.tolist() == pytest.approx([0.15, 0.6])


@pytest.mark.parametrize("encoder", ["cnn", "random"])
@pytest.mark.parametrize("bootstrap", [0.0, 0.7])
def test_batched_recompute_equals_per_step_graph(encoder, bootstrap):
    torch.manual_seed(0)
    cfg = NetConfig(encoder=encoder, obs_size_px=32, hidden_size=32, lstm_size=32)
    model = ActorCritic(cfg)
    T = 7
    if encoder == "cnn":
        views = [torch.randint(0, 256, (32, 32, 3), dtype=torch.uint8) for _ in range(T)]
        target = torch.randint(0, 256, (32, 32, 3), dtype=torch.uint8)
    else:
        fdim = model.obs_embed.in_features
        views = [torch.randn(fdim) for _ in range(T)]
        target = torch.randn(fdim)
    actions = [int(a) for a in torch.randint(0, 4, (T,))]
    rewards = [-0.01] * (T - 1) + [5.0]
    start = tuple(torch.randn(1, 32) * 0.1 for _ in range(2)) + (torch.softmax(
        torch.randn(1, 4), -1),)

    # The slow path: a graph kept step by step, as SAVN/ISAR do.
    state = start
    logits, values = [], []
    for t in range(T):
        lg, v, state = model(views[t][None, None], target[None], state)
        logits.append(lg[0, 0])
        values.append(v[0, 0])
    slow = actor_critic_loss(torch.stack(logits), torch.stack(values), actions, rewards,
                             bootstrap)
    g_slow = torch.autograd.grad(slow.total, list(model.parameters()))

    ro = Rollout(start, target, views, actions, rewards)
    fast = rollout_loss(model, ro, bootstrap, A3CConfig())
    g_fast = torch.autograd.grad(fast.total, list(model.parameters()))
    assert fast.total.item() == pytest.approx(slow.total.item(), rel=1e-5, abs=1e-5)
    for (name, _), a, b in zip(model.named_parameters(), g_slow, g_fast, strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5), name

    # ...and through functional_call with a parameter dict.
    params = {k: v.detach().clone().requires_grad_() for k, v in model.named_parameters()}
    func = rollout_loss(model, ro, bootstrap, A3CConfig(), params=params)
    assert func.total.item() == pytest.approx(fast.total.item(), rel=1e-6)


def _ppo_case(seed=0, T=6, B=4, A=4):
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(T, B, A, generator=g, dtype=torch.float64, requires_grad=True)
    values = torch.randn(T, B, generator=g, dtype=torch.float64, requires_grad=True)
    actions = torch.randint(0, A, (T, B), generator=g)
    returns = torch.randn(T, B, generator=g, dtype=torch.float64)
    adv = torch.randn(T, B, generator=g, dtype=torch.float64)
    weights = torch.rand(T, B, generator=g, dtype=torch.float64)
    log_pi = torch.log_softmax(logits, -1).gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    return logits, values, actions, returns, adv, weights, log_pi.detach(), g


def test_ppo_surrogate_gradient_is_the_a3c_term_at_ratio_one():
    """ISAR's PPO base on its first pass: the acting log-probs are the current ones, the
    ratio is 1 and the clipped surrogate's gradient is the A3C policy-gradient term's
    -A grad log pi (float64; values and entropy are the same terms in both)."""
    logits, values, actions, returns, adv, w, old, _ = _ppo_case()
    cfg = LossConfig()
    a3c = policy_value_terms(logits, values, actions, returns, adv, cfg, weights=w)
    ppo = policy_value_terms(logits, values, actions, returns, adv, cfg, weights=w,
                             old_log_probs=old, clip_coef=0.2)
    # the values differ (-rho A = -A against -A log pi), the gradients do not
    assert float(ppo.total.detach()) == pytest.approx(
        float(a3c.total.detach() + (w * adv * (old - 1.0)).sum()), rel=1e-12)
    ga = torch.autograd.grad(a3c.total, (logits, values))
    gp = torch.autograd.grad(ppo.total, (logits, values))
    for a, b in zip(ga, gp, strict=True):
        torch.testing.assert_close(b, a, atol=1e-12, rtol=1e-12)


def test_ppo_surrogate_gradient_where_clipped_and_not():
    """Away from ratio 1: -rho A grad log pi where the clip is inactive, 0 where it is
    active (rho > 1 + eps with A > 0, rho < 1 - eps with A < 0); the A3C term with the
    advantages so rescaled has the same gradient (float64)."""
    logits, values, actions, returns, adv, w, lp, g = _ppo_case(seed=1)
    old = lp + 0.8 * (torch.rand(lp.shape, generator=g, dtype=torch.float64) - 0.5)
    rho = (lp - old).exp()
    clipped = ((rho > 1.2) & (adv > 0)) | ((rho < 0.8) & (adv < 0))
    assert 0 < int(clipped.sum()) < clipped.numel()
    cfg = LossConfig()
    ppo = policy_value_terms(logits, values, actions, returns, adv, cfg, weights=w,
                             old_log_probs=old, clip_coef=0.2)
    like = policy_value_terms(logits, values, actions, returns,
                              torch.where(clipped, 0.0, rho * adv), cfg, weights=w)
    for a, b in zip(torch.autograd.grad(like.total, (logits, values)),
                    torch.autograd.grad(ppo.total, (logits, values)), strict=True):
        torch.testing.assert_close(b, a, atol=1e-12, rtol=1e-12)
