"""The actor-critic: shapes, SAVN's init, module vs functional forward, second-order grads."""

from __future__ import annotations

import pytest
import torch
from torch.func import functional_call

from geonav.errors import ConfigError
from geonav.policy.config import NetConfig
from geonav.policy.model import ActorCritic, param_dict


def _inputs(model: ActorCritic, T: int = 3, B: int = 2):
    n = model.cfg.obs_size_px
    g = torch.Generator().manual_seed(1)
    obs = torch.randint(0, 256, (T, B, n, n, 3), dtype=torch.uint8, generator=g)
    tgt = torch.randint(0, 256, (B, n, n, 3), dtype=torch.uint8, generator=g)
    return obs, tgt, model.initial_state(B)


def test_shapes_and_state():
    model = ActorCritic(NetConfig(obs_size_px=64))
    obs, tgt, st = _inputs(model)
    logits, values, (h, c, p) = model(obs, tgt, st)
    assert logits.shape == (3, 2, 4) and values.shape == (3, 2)
    assert h.shape == (2, 128) and c.shape == (2, 128)
    assert torch.allclose(p, torch.softmax(logits[-1], -1))
    assert model.obs_embed.out_features == 64 and model.action_embed.out_features == 10


def test_savn_init():
    torch.manual_seed(0)
    model = ActorCritic(NetConfig(obs_size_px=32, init="savn", input_norm="none"))
    assert torch.allclose(model.actor.weight.norm(dim=1), torch.full((4,), 0.01), atol=1e-6)
    assert torch.allclose(model.critic.weight.norm(dim=1), torch.ones(1), atol=1e-6)
    for b in (model.actor.bias, model.critic.bias, model.lstm.bias_ih, model.fc.bias):
        assert torch.count_nonzero(b) == 0
    # A fresh policy is close to uniform.
    obs, tgt, st = _inputs(model)
    logits, _, _ = model(obs, tgt, st)
    assert torch.softmax(logits, -1).sub(0.25).abs().max() < 0.02


def test_default_init_keeps_the_signal_and_depends_on_the_view():
    """Issue 10: orthogonal ReLU-gain init, centred inputs and an actor of norm 1, so the
    fresh policy's logits already differ between views (the SAVN init's do not)."""
    torch.manual_seed(0)
    model = ActorCritic(NetConfig(obs_size_px=32))
    assert torch.allclose(model.actor.weight.norm(dim=1), torch.ones(4), atol=1e-5)
    for b in (model.actor.bias, model.critic.bias, model.lstm.bias_ih, model.fc.bias):
        assert torch.count_nonzero(b) == 0
    w = model.fc.weight
    assert torch.allclose(w @ w.T, 2.0 * torch.eye(w.shape[0]), atol=1e-4)  # orthogonal, gain^2
    g = torch.Generator().manual_seed(1)
    obs = torch.randint(0, 256, (1, 6, 32, 32, 3), dtype=torch.uint8, generator=g)
    tgt = torch.randint(0, 256, (6, 32, 32, 3), dtype=torch.uint8, generator=g)
    spread = {}
    for init, norm in (("orthogonal", "center"), ("savn", "none")):
        torch.manual_seed(0)
        m = ActorCritic(NetConfig(obs_size_px=32, init=init, input_norm=norm))
        logits, _, _ = m(obs, tgt, m.initial_state(6))
        spread[init] = float(logits[0].detach().std(0).mean())
    assert spread["orthogonal"] > 0.05 > 100 * spread["savn"]
    with pytest.raises(ConfigError):
        NetConfig(init="xavier")
    with pytest.raises(ConfigError):
        NetConfig(input_norm="imagenet")


def test_steps_one_by_one_equal_one_sequence_call():
    model = ActorCritic(NetConfig(obs_size_px=32, hidden_size=32, lstm_size=32))
    obs, tgt, st = _inputs(model, T=4)
    seq_logits, seq_values, seq_state = model(obs, tgt, st)
    state = st
    for t in range(4):
        lg, v, state = model(obs[t:t + 1], tgt, state)
        assert torch.allclose(lg[0], seq_logits[t], atol=1e-6)
        assert torch.allclose(v[0], seq_values[t], atol=1e-6)
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(state, seq_state, strict=True))


@pytest.mark.parametrize("encoder", ["cnn", "random"])
def test_functional_call_agrees_with_module(encoder):
    torch.manual_seed(0)
    model = ActorCritic(NetConfig(encoder=encoder, obs_size_px=32, hidden_size=32,
                                  lstm_size=32))
    if encoder == "cnn":
        obs, tgt, st = _inputs(model)
    else:
        f = model.obs_embed.in_features
        obs, tgt, st = torch.randn(3, 2, f), torch.randn(2, f), model.initial_state(2)
    out_m = model(obs, tgt, st)
    params = {k: v.detach().clone() for k, v in param_dict(model).items()}
    out_f = functional_call(model, params, (obs, tgt, st), strict=True)
    assert torch.equal(out_m[0], out_f[0]) and torch.equal(out_m[1], out_f[1])
    # Adapted parameters (theta' = theta - alpha g) change the output and keep the graph.
    theta = {k: v.requires_grad_() for k, v in params.items()}
    loss = functional_call(model, theta, (obs, tgt, st), strict=True)[1].pow(2).sum()
    grads = torch.autograd.grad(loss, list(theta.values()), create_graph=True)
    adapted = {k: v - 0.1 * g for (k, v), g in zip(theta.items(), grads, strict=True)}
    out_a = functional_call(model, adapted, (obs, tgt, st), strict=True)
    assert not torch.allclose(out_a[1], out_m[1])
    meta_grad = torch.autograd.grad(out_a[1].sum(), theta["critic.weight"])[0]
    assert torch.isfinite(meta_grad).all() and meta_grad.abs().sum() > 0


def test_bad_config():
    with pytest.raises(ConfigError, match="encoder"):
        NetConfig(encoder="vgg")
    with pytest.raises(ConfigError, match="obs_size_px"):
        NetConfig(obs_size_px=8)
