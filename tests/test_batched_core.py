"""The batched forward against the reference functional path, float64, to 1e-10.

These tests are the guard of ``ActorCritic.forward``'s one batched mirror
(geonav/policy/batched/core.py): a change to the network's forward that is not mirrored
there fails here. Slots are on different tasks (targets) and at different steps of their
episodes (non-zero start states, episode starts inside the sequence).
"""

import numpy as np
import pytest
import torch

from geonav.policy.batched.core import (
    ENCODER,
    LAYERS,
    Recorder,
    encode_slots,
    encoder_weights,
    factored_forward,
    factored_step,
    sequence_forward,
)
from geonav.policy.config import LossConfig
from geonav.policy.functional import sgd_step
from geonav.policy.losses import (
    actor_critic_loss,
    gae_returns,
    policy_value_terms,
    returns_and_advantages,
)
from geonav.policy.model import ActorCritic
from geonav.policy.testing import tiny_net

TOL = 1e-10  # absolute and relative
LOSS = LossConfig()


@pytest.fixture(scope="module")
def setup():
    return _table_setup(tiny_net("random", 32, size=16), 0, 50.0)


def _table_setup(net, seed, actor_scale):
    """A float64 network on a frozen feature table (12 random rows) with non-trivial
    actor/critic heads (SAVN's init makes them tiny)."""
    torch.manual_seed(seed)
    model = ActorCritic(net).double()
    with torch.no_grad():
        model.actor.weight.mul_(actor_scale)
        model.actor.bias.normal_()
        model.critic.bias.normal_()
    g = torch.Generator().manual_seed(seed + 1)
    table = torch.rand(12, model.obs_embed.in_features, generator=g, dtype=torch.float64)
    return model, table


@pytest.fixture(scope="module")
def cnn_setup():
    """The trainable CNN inside the network; the 'table' holds uint8 views (the CNN
    adapts per slot in the inner steps)."""
    return _cnn_setup("small", 32)


@pytest.fixture(scope="module")
def nature_setup():
    """The three-convolution ('nature') trainable CNN, at 40 px (it needs >= 36)."""
    return _cnn_setup("nature", 40)


def _cnn_setup(kind, px):
    from dataclasses import replace

    torch.manual_seed(2)
    model = ActorCritic(replace(tiny_net("cnn", px, size=16), cnn=kind)).double()
    with torch.no_grad():  # features of order 1: the gradients' float64 rounding ~1e-12
        for p in model.encoder.parameters():
            p.mul_(0.3)
        model.actor.weight.mul_(50.0)
        model.actor.bias.normal_()
        model.critic.bias.normal_()
    g = torch.Generator().manual_seed(3)
    images = torch.randint(0, 256, (12, px, px, 3), generator=g, dtype=torch.uint8)
    return model, images


@pytest.fixture(scope="module")
def ff_setup():
    """The feed-forward network (NetConfig.recurrent=False: no LSTM, no previous-action
    input) on a frozen feature table; a smaller actor scale (no LSTM squashes the logits,
    so float64 rounding grows with it)."""
    from dataclasses import replace

    return _table_setup(replace(tiny_net("random", 32, size=16), recurrent=False), 4, 5.0)


@pytest.fixture(scope="module")
def ffsc_setup():
    """The feed-forward network with its own FC layer for the critic (separate_critic)."""
    from dataclasses import replace

    return _table_setup(replace(tiny_net("random", 32, size=16), recurrent=False,
                                separate_critic=True), 4, 5.0)


def _nets(request, kind):
    return request.getfixturevalue({"cnn": "cnn_setup", "ff": "ff_setup",
                                    "ffsc": "ffsc_setup"}.get(kind, "setup"))


def _feats(model, params, adapted, table, rows, rec=None):
    """(B, F) features of one view per slot under the slots' adapted weights: the frozen
    table's rows, or each slot's view encoded by the CNN with its own weights."""
    if model.encoder is None:
        return table[rows]
    w = encoder_weights(params, adapted, rows.shape[0])
    if rec is not None:
        rec.add_encoder(w)
    return encode_slots(model.encoder, w, table[rows].unsqueeze(1))[:, 0]


def _state(model, b, g):
    h = torch.randn(b, model.cfg.lstm_size, generator=g, dtype=torch.float64)
    c = torch.randn(b, model.cfg.lstm_size, generator=g, dtype=torch.float64)
    p = torch.softmax(torch.randn(b, model.cfg.n_actions, generator=g, dtype=torch.float64), -1)
    return h, c, p


def _ref_slot(model, params, table, views, target, state):
    """functional_call of the module on one slot's steps (T,) from its state."""
    args = (table[views].unsqueeze(1), table[target].unsqueeze(0), state)
    logits, values, end = torch.func.functional_call(model, params, args, strict=True)
    return logits[:, 0], values[:, 0], end


@pytest.mark.parametrize("b,kind", [(1, "random"), (5, "random"), (5, "ff"),
                                    (5, "ffsc")])
def test_sequence_forward_equals_module(request, b, kind):
    model, table = _nets(request, kind)
    g = torch.Generator().manual_seed(b)
    T = 7
    views = torch.randint(0, table.shape[0], (T, b), generator=g)
    targets = torch.randint(0, table.shape[0], (T, b), generator=g)
    starts = torch.zeros(T, b, dtype=torch.bool)
    if b > 1:
        starts[3, 1] = starts[5, 3] = True  # slots 1 and 3 begin new episodes mid-sequence
    for s in range(b):  # a target is constant within an episode
        for t in range(1, T):
            if not starts[t, s]:
                targets[t, s] = targets[t - 1, s]
    state = _state(model, b, g)
    params = dict(model.named_parameters())
    logits, values, end = sequence_forward(params, model.cfg.embed_dim, table, views, targets,
                                           state, starts)
    for s in range(b):
        st = (state[0][s:s + 1], state[1][s:s + 1], state[2][s:s + 1])
        cuts = [0] + [t for t in range(1, T) if starts[t, s]] + [T]
        for t0, t1 in zip(cuts, cuts[1:], strict=False):
            if t0 > 0:
                st = model.initial_state(1)
                st = tuple(x.double() for x in st)
            lg, v, st = _ref_slot(model, params, table, views[t0:t1, s], targets[t0, s], st)
            torch.testing.assert_close(logits[t0:t1, s], lg, atol=TOL, rtol=TOL)
            torch.testing.assert_close(values[t0:t1, s], v, atol=TOL, rtol=TOL)
        torch.testing.assert_close(end[0][s], st[0][0], atol=TOL, rtol=TOL)
    # the gradient flows into the parameters through the once-per-view image part
    logits.sum().backward()
    assert model.obs_embed.weight.grad is not None and model.obs_embed.weight.grad.abs().sum() > 0
    model.zero_grad(set_to_none=True)


@pytest.mark.parametrize("b,kind", [(1, "cnn_setup"), (5, "cnn_setup"),
                                    (3, "nature_setup")])
def test_cnn_forward_with_per_slot_weights_equals_module(request, b, kind):
    """The trainable CNN (both kinds) under per-slot weights theta_s = phi + delta_s (the
    encoder's SlotDeltas and the linear layers' factors) equals functional_call with
    theta_s."""
    from geonav.policy.batched.core import Factors, SlotDeltas

    model, images = request.getfixturevalue(kind)
    g = torch.Generator().manual_seed(b)
    phi = dict(model.named_parameters())
    delta = {n[len("encoder."):]: 0.05 * torch.randn(b, *p.shape, generator=g,
                                                     dtype=torch.float64)
             for n, p in phi.items() if n.startswith("encoder.")}
    fc_u = torch.randn(b, 2, model.fc.out_features, generator=g, dtype=torch.float64)
    fc_v = torch.randn(b, 2, model.fc.in_features, generator=g, dtype=torch.float64)
    adapted = {ENCODER: SlotDeltas(delta), "fc": Factors().add(fc_u, fc_v, 0.1)}
    T = 4
    views = torch.randint(0, 12, (T, b), generator=g)
    targets = torch.randint(0, 12, (b,), generator=g)
    state = _state(model, b, g)
    st = state
    tgt_f = _feats(model, phi, adapted, images, targets)
    logits = []
    for t in range(T):
        lg, _, st = factored_step(phi, model.cfg.embed_dim,
                                  _feats(model, phi, adapted, images, views[t]), tgt_f, st,
                                  adapted)
        logits.append(lg)
    dw, db = adapted["fc"].dense()
    for s in range(b):
        theta = dict(phi)
        theta.update({f"encoder.{n}": phi[f"encoder.{n}"] + d[s] for n, d in delta.items()})
        theta["fc.weight"], theta["fc.bias"] = phi["fc.weight"] + dw[s], phi["fc.bias"] + db[s]
        lg, _, _ = _ref_slot(model, theta, images, views[:, s], targets[s],
                             (state[0][s:s + 1], state[1][s:s + 1], state[2][s:s + 1]))
        torch.testing.assert_close(torch.stack(logits)[:, s], lg, atol=TOL, rtol=TOL)


def _window_data(model, table, b, n_steps, k_segs, seed):
    g = torch.Generator().manual_seed(seed)
    T = n_steps * k_segs
    views = torch.randint(0, table.shape[0], (T, b), generator=g)
    targets = torch.randint(0, table.shape[0], (b,), generator=g)
    actions = torch.randint(0, model.cfg.n_actions, (T, b), generator=g)
    rewards = torch.where(torch.rand(T, b, generator=g) < 0.2, 5.0, -0.01).double()
    return views, targets, actions, rewards, _state(model, b, g)


def _batched_segment_loss(logits, values, actions, rewards, bootstrap, old=None):
    ret, adv = gae_returns(rewards.numpy(), values.detach().numpy(), bootstrap.numpy(), None,
                           LOSS.gamma, LOSS.tau)
    return policy_value_terms(logits, values, actions, torch.from_numpy(ret),
                              torch.from_numpy(adv), LOSS, old_log_probs=old).total


def _log_pi(logits, actions):
    return torch.log_softmax(logits, -1).gather(-1, actions.unsqueeze(-1)).squeeze(-1)


def _batched_window(model, table, data, n_steps, k_segs, alpha, second_order, record=None,
                    gram=False, old=None, logps=None):
    """phi -> K segments of N steps with an inner step per segment but the last, per slot;
    returns the window loss summed over slots (graph to phi). ``old``: per segment the
    (N, B) acting log-probs of ISAR's PPO base (None: the A3C base); ``logps`` collects
    each segment's detached log pi(a_t)."""
    views, targets, actions, rewards, state = data
    params = dict(model.named_parameters())
    adapted = {}
    total = 0.0
    g = table @ table.T if gram else None
    for k in range(k_segs):
        sl = slice(k * n_steps, (k + 1) * n_steps)
        rec = Recorder(gram=g)
        tgt_f = _feats(model, params, adapted, table, targets, rec)  # once per theta
        logits, values = [], []
        for t in range(sl.start, sl.stop):
            lg, v, state = factored_step(params, model.cfg.embed_dim,
                                         _feats(model, params, adapted, table, views[t], rec),
                                         tgt_f, state, adapted, rec, None,
                                         views[t] if gram else None, targets if gram else None)
            logits.append(lg)
            values.append(v)
        logits, values = torch.stack(logits), torch.stack(values)
        nxt = views[sl.stop % views.shape[0]]
        with torch.no_grad():  # bootstrap V(s_next) without advancing the state
            _, v_next, _ = factored_step(params, model.cfg.embed_dim,
                                         _feats(model, params, adapted, table, nxt), tgt_f,
                                         state, adapted, None, None, nxt if gram else None,
                                         targets if gram else None)
            v_next = v_next[None]
        if logps is not None:
            logps.append(_log_pi(logits, actions[sl]).detach())
        loss = _batched_segment_loss(logits, values, actions[sl], rewards[sl], v_next[0],
                                     None if old is None else old[k])
        total = total + loss
        if k < k_segs - 1:
            adapted = rec.inner_factors(loss, adapted, alpha, create_graph=second_order)
            if record is not None:
                record.append(adapted)
    return total


def _ref_window(model, table, data, n_steps, k_segs, alpha, second_order, old=None):
    """The same per slot with functional_call and explicitly adapted parameters."""
    views, targets, actions, rewards, state = data
    phi = dict(model.named_parameters())
    total, thetas = 0.0, []
    for s in range(views.shape[1]):
        theta = dict(phi)
        st = (state[0][s:s + 1], state[1][s:s + 1], state[2][s:s + 1])
        slot_thetas = []
        for k in range(k_segs):
            sl = slice(k * n_steps, (k + 1) * n_steps)
            lg, v, st = _ref_slot(model, theta, table, views[sl, s], targets[s], st)
            with torch.no_grad():
                _, v_next, _ = _ref_slot(model, theta, table,
                                         views[sl.stop % views.shape[0], s][None], targets[s], st)
            if old is None:
                loss = actor_critic_loss(lg, v, actions[sl, s], rewards[sl, s],
                                         float(v_next[0]), LOSS).total
            else:  # ISAR's PPO base: the clipped surrogate against the acting log-probs
                ret, adv = returns_and_advantages(rewards[sl, s], v, float(v_next[0]),
                                                  LOSS.gamma, LOSS.tau)
                loss = policy_value_terms(lg, v, actions[sl, s], ret, adv, LOSS,
                                          old_log_probs=old[k][:, s]).total
            total = total + loss
            if k < k_segs - 1:
                theta = sgd_step(theta, loss, alpha, create_graph=second_order)
                slot_thetas.append(theta)
        thetas.append(slot_thetas)
    return total, thetas


@pytest.mark.parametrize("b,gram,kind", [(1, False, "random"), (5, False, "random"),
                                         (5, True, "random"), (1, False, "cnn"),
                                         (5, False, "cnn"), (5, False, "ff"),
                                         (5, False, "ffsc")])
def test_inner_updates_equal_functional_call(request, b, gram, kind):
    """Per-slot adapted weights after each inner step equal theta - alpha grad (dense),
    the trainable CNN's included."""
    model, table = _nets(request, kind)
    alpha = 0.3  # large, so that an error in the factors shows
    data = _window_data(model, table, b, 3, 3, seed=10 + b)
    adapted_log = []
    _batched_window(model, table, data, 3, 3, alpha, True, adapted_log, gram=gram)
    _, thetas = _ref_window(model, table, data, 3, 3, alpha, True)
    phi = dict(model.named_parameters())
    for k, adapted in enumerate(adapted_log):
        for key, (wn, bn) in LAYERS.items():
            if wn not in phi:  # no previous-view slot in this network
                continue
            dw, db = adapted[key].dense(table)
            for s in range(b):
                torch.testing.assert_close(phi[wn] + dw[s], thetas[s][k][wn], atol=TOL, rtol=TOL)
                torch.testing.assert_close(phi[bn] + db[s], thetas[s][k][bn], atol=TOL, rtol=TOL)
        enc = [n for n in phi if n.startswith("encoder.")]
        assert (ENCODER in adapted) == bool(enc)
        for n in enc:
            delta = adapted[ENCODER].delta[n[len("encoder."):]]
            for s in range(b):
                torch.testing.assert_close(phi[n] + delta[s], thetas[s][k][n], atol=TOL,
                                           rtol=TOL)
                assert float((thetas[s][k][n] - phi[n]).detach().abs().max()) > 1e-8  # adapts


@pytest.mark.parametrize("b,second_order,gram,kind", [
    (1, True, False, "random"), (5, True, False, "random"), (5, False, False, "random"),
    (5, True, True, "random"), (5, False, True, "random"), (1, True, False, "cnn"),
    (5, True, False, "cnn"), (5, False, False, "cnn"), (5, True, False, "ff"),
    (5, True, False, "ffsc")])
def test_window_gradient_equals_functional_call(request, b, second_order, gram, kind):
    """ISAR's window gradient w.r.t. phi (second and first order), summed over slots; the
    view embeddings' factors dense or as table rows with the Gram matrix; the trainable
    CNN adapted per slot."""
    model, table = _nets(request, kind)
    data = _window_data(model, table, b, 2, 3, seed=20 + b)
    phi = list(model.parameters())
    got = torch.autograd.grad(_batched_window(model, table, data, 2, 3, 0.3, second_order,
                                              gram=gram), phi)
    ref_loss, _ = _ref_window(model, table, data, 2, 3, 0.3, second_order)
    ref = torch.autograd.grad(ref_loss, phi)
    for a, r in zip(got, ref, strict=True):
        torch.testing.assert_close(a, r, atol=TOL, rtol=TOL)
    if second_order:  # the second-order terms matter at this alpha: first order differs
        fo = torch.autograd.grad(_batched_window(model, table, data, 2, 3, 0.3, False), phi)
        assert max(float((x - y).abs().max()) for x, y in zip(fo, got, strict=True)) > 1e-6


@pytest.mark.parametrize("b,second_order", [(1, True), (5, True), (1, False), (5, False)])
def test_ppo_base_window_gradient_equals_functional_call(setup, b, second_order):
    """ISAR's PPO base (docs/learning.md): the window gradient w.r.t. phi, second and
    first order, with acting log-probs off the current ones by up to 0.3 in log (a pass
    after the first: ratios away from 1, some clipped at eps = 0.2)."""
    model, table = setup
    data = _window_data(model, table, b, 2, 3, seed=40 + b)
    phi = list(model.parameters())
    logps = []
    _batched_window(model, table, data, 2, 3, 0.3, False, logps=logps)
    g = torch.Generator().manual_seed(b)
    old = [lp + 0.6 * (torch.rand(lp.shape, generator=g, dtype=torch.float64) - 0.5)
           for lp in logps]
    got = torch.autograd.grad(_batched_window(model, table, data, 2, 3, 0.3, second_order,
                                              old=old), phi)
    ref_loss, _ = _ref_window(model, table, data, 2, 3, 0.3, second_order, old=old)
    ref = torch.autograd.grad(ref_loss, phi)
    for a, r in zip(got, ref, strict=True):
        torch.testing.assert_close(a, r, atol=TOL, rtol=TOL)
    a3c = torch.autograd.grad(_batched_window(model, table, data, 2, 3, 0.3, second_order),
                              phi)  # the surrogate away from ratio 1 is another gradient
    assert max(float((x - y).abs().max()) for x, y in zip(a3c, got, strict=True)) > 1e-6


def test_masked_gae_equals_per_episode_segments():
    """An episode end inside a (T, B) sequence splits it into independent segments."""
    rng = np.random.default_rng(0)
    T, b = 9, 3
    r = rng.normal(size=(T, b))
    v = rng.normal(size=(T, b))
    ends = np.zeros((T, b), bool)
    ends[3, 0] = ends[6, 2] = ends[8, 1] = True
    boot = rng.normal(size=b)
    ret, adv = gae_returns(r, v, np.where(ends[-1], 0.0, boot), ends, 0.9, 0.8)
    for s in range(b):
        cuts = [0] + [t + 1 for t in range(T) if ends[t, s]]
        if cuts[-1] != T:
            cuts.append(T)
        for t0, t1 in zip(cuts, cuts[1:], strict=False):
            bs = 0.0 if ends[t1 - 1, s] else boot[s]
            r1, a1 = gae_returns(r[t0:t1, s:s + 1], v[t0:t1, s:s + 1], np.array([bs]), None,
                                 0.9, 0.8)
            np.testing.assert_allclose(ret[t0:t1, s], r1[:, 0], atol=1e-12)
            np.testing.assert_allclose(adv[t0:t1, s], a1[:, 0], atol=1e-12)


@pytest.mark.parametrize("b,kind", [(1, "random"), (5, "random"), (1, "cnn"), (5, "cnn"),
                                    (1, "cnn-prev"), (3, "cnn-prev")])
def test_savn_episode_meta_gradient_equals_functional_call(request, b, kind):
    """SAVN: inner steps on the learned loss (TCN over [h, pi]), meta-loss L_AC over the
    episode; gradient w.r.t. phi and Lambda, slots on different targets and states; the
    trainable CNN adapted per slot (cnn-prev: its previous-altitude views in the extra
    slot, encoded under theta_s too)."""
    from torch.nn import functional as F

    from geonav.policy.functional import segment_forward
    from geonav.policy.savn import InteractionLoss

    if kind == "cnn-prev":
        model, table, prev = request.getfixturevalue("cnn_prev_setup")
    else:
        (model, table), prev = _nets(request, kind), None
    torch.manual_seed(7)
    tcn = InteractionLoss(3, 4).double()
    k, segs, alpha = 3, 3, 0.3
    views, targets, actions, rewards, state = _window_data(model, table, b, k, segs, seed=30 + b)
    lam = dict(tcn.named_parameters())
    leaves = list(model.parameters()) + list(tcn.parameters())
    # batched
    params, adapted, st = dict(model.named_parameters()), {}, state
    logits, values = [], []
    for s_ in range(segs):
        sl = slice(s_ * k, (s_ + 1) * k)
        rec, hs, lgs = Recorder(), [], []
        tgt_f = _feats(model, params, adapted, table, targets, rec)
        for t in range(sl.start, sl.stop):
            pf = None if prev is None else _feats(model, params, adapted, prev, views[t], rec)
            lg, v, st = factored_step(params, model.cfg.embed_dim,
                                      _feats(model, params, adapted, table, views[t], rec),
                                      tgt_f, st, adapted, rec, prev_f=pf)
            hs.append(st[0])
            lgs.append(lg)
            logits.append(lg)
            values.append(v)
        if s_ < segs - 1:
            rows = torch.cat([torch.stack(hs, 1), F.softmax(torch.stack(lgs, 1), -1)], -1)
            l_int = torch.func.vmap(
                lambda r: torch.func.functional_call(tcn, lam, (r,)))(rows).sum()
            adapted = rec.inner_factors(l_int, adapted, alpha, create_graph=True)
    meta = _batched_segment_loss(torch.stack(logits), torch.stack(values), actions, rewards,
                                 torch.zeros(b, dtype=torch.float64))
    got = torch.autograd.grad(meta, leaves)
    # reference: functional_call with explicitly adapted parameters, slot by slot
    ref_total = 0.0
    for s in range(b):
        theta = dict(model.named_parameters())
        st = (state[0][s:s + 1], state[1][s:s + 1], state[2][s:s + 1])
        lgs, vs = [], []
        for s_ in range(segs):
            sl = slice(s_ * k, (s_ + 1) * k)
            lg, v, hs, st = segment_forward(model, theta, table[views[sl, s]],
                                            table[targets[s]], st, hidden=True,
                                            prev=None if prev is None else prev[views[sl, s]])
            lgs.append(lg)
            vs.append(v)
            if s_ < segs - 1:
                theta = sgd_step(theta, tcn(torch.cat([hs, F.softmax(lg, -1)], -1)), alpha,
                                 create_graph=True)
        ref_total = ref_total + actor_critic_loss(torch.cat(lgs), torch.cat(vs), actions[:, s],
                                                  rewards[:, s], 0.0, LOSS).total
    ref = torch.autograd.grad(ref_total, leaves)
    for a, r in zip(got, ref, strict=True):
        torch.testing.assert_close(a, r, atol=TOL, rtol=TOL)
    assert float(got[-1].abs().sum()) > 0  # Lambda gets its second-order gradient


@pytest.fixture(scope="module")
def prev_setup():
    """A network with the extra previous-altitude slot, and a second feature table."""
    from dataclasses import replace

    torch.manual_seed(3)
    model = ActorCritic(replace(tiny_net("random", 32, size=16), prev_view_input=True)).double()
    with torch.no_grad():
        model.actor.weight.mul_(50.0)
        model.prev_embed.bias.normal_()  # zero-filled slot: ReLU(bias) must show
    g = torch.Generator().manual_seed(5)
    table = torch.rand(12, model.obs_embed.in_features, generator=g, dtype=torch.float64)
    prev = torch.rand(12, model.obs_embed.in_features, generator=g, dtype=torch.float64)
    return model, table, prev


@pytest.mark.parametrize("with_views", [False, True])
def test_prev_slot_forward_equals_module(prev_setup, with_views):
    model, table, prev = prev_setup
    g = torch.Generator().manual_seed(2)
    T, b = 5, 4
    views = torch.randint(0, 12, (T, b), generator=g)
    targets = torch.randint(0, 12, (b,), generator=g)
    state = _state(model, b, g)
    params = dict(model.named_parameters())
    pv = prev if with_views else None
    logits, values, _ = sequence_forward(params, model.cfg.embed_dim, table, views, targets,
                                         state, None, pv)
    lf, vf, _ = factored_forward(params, model.cfg.embed_dim, table[views],
                                 table[targets].expand(T, -1, -1), state, {}) \
        if not with_views else (None, None, None)
    for s in range(b):
        st = (state[0][s:s + 1], state[1][s:s + 1], state[2][s:s + 1])
        args = (table[views[:, s]].unsqueeze(1), table[targets[s]][None], st)
        if with_views:
            args = (*args, prev[views[:, s]].unsqueeze(1))
        lg, v, _ = torch.func.functional_call(model, params, args, strict=True)
        torch.testing.assert_close(logits[:, s], lg[:, 0], atol=TOL, rtol=TOL)
        torch.testing.assert_close(values[:, s], v[:, 0], atol=TOL, rtol=TOL)
        if lf is not None:
            torch.testing.assert_close(lf[:, s], lg[:, 0], atol=TOL, rtol=TOL)


@pytest.fixture(scope="module")
def cnn_prev_setup():
    """The trainable CNN with the extra previous-altitude slot, and uint8 views of the
    cells at both altitudes (the CNN encodes both under the slots' adapted weights)."""
    from dataclasses import replace

    torch.manual_seed(4)
    model = ActorCritic(replace(tiny_net("cnn", 20, size=16), prev_view_input=True)).double()
    with torch.no_grad():
        for p in model.encoder.parameters():
            p.mul_(0.3)
        model.actor.weight.mul_(50.0)
        model.actor.bias.normal_()
        model.critic.bias.normal_()
    g = torch.Generator().manual_seed(6)
    images = torch.randint(0, 256, (12, 20, 20, 3), generator=g, dtype=torch.uint8)  # fast
    prev = torch.randint(0, 256, (12, 20, 20, 3), generator=g, dtype=torch.uint8)
    return model, images, prev


@pytest.mark.parametrize("b,kind", [(4, "random"), (1, "cnn"), (3, "cnn")])
def test_prev_slot_window_gradient_equals_functional_call(request, b, kind):
    """Second-order ISAR window with the previous-altitude views in the extra slot (the
    trainable CNN: encoded under each slot's adapted weights, as its current views)."""
    model, table, prev = request.getfixturevalue("cnn_prev_setup" if kind == "cnn" else
                                                 "prev_setup")
    n, k, alpha = 2, 2 if kind == "cnn" else 3, 0.3  # the CNN's: one inner step, fast
    views, targets, actions, rewards, state = _window_data(model, table, b, n, k, seed=41)
    params = dict(model.named_parameters())
    adapted, st, total = {}, state, 0.0
    for j in range(k):
        rec, lgs, vs = Recorder(), [], []
        tgt_f = _feats(model, params, adapted, table, targets, rec)
        for t in range(j * n, (j + 1) * n):
            lg, v, st = factored_step(params, model.cfg.embed_dim,
                                      _feats(model, params, adapted, table, views[t], rec),
                                      tgt_f, st, adapted, rec,
                                      prev_f=_feats(model, params, adapted, prev, views[t], rec))
            lgs.append(lg)
            vs.append(v)
        nxt = views[((j + 1) * n) % views.shape[0]]
        with torch.no_grad():
            _, v_next, _ = factored_step(params, model.cfg.embed_dim,
                                         _feats(model, params, adapted, table, nxt), tgt_f, st,
                                         adapted, prev_f=_feats(model, params, adapted, prev,
                                                                nxt))
        loss = _batched_segment_loss(torch.stack(lgs), torch.stack(vs),
                                     actions[j * n:(j + 1) * n], rewards[j * n:(j + 1) * n],
                                     v_next)
        total = total + loss
        if j < k - 1:
            adapted = rec.inner_factors(loss, adapted, alpha, create_graph=True)
    got = torch.autograd.grad(total, list(model.parameters()))
    ref_total = 0.0
    for s in range(b):
        theta = dict(params)
        st = (state[0][s:s + 1], state[1][s:s + 1], state[2][s:s + 1])
        for j in range(k):
            sl = slice(j * n, (j + 1) * n)
            args = (table[views[sl, s]].unsqueeze(1), table[targets[s]][None], st,
                    prev[views[sl, s]].unsqueeze(1))
            lg, v, st = torch.func.functional_call(model, theta, args, strict=True)
            nxt = views[sl.stop % views.shape[0], s]
            with torch.no_grad():
                _, v_next, _ = torch.func.functional_call(
                    model, theta, (table[nxt][None, None], table[targets[s]][None], st,
                                   prev[nxt][None, None]), strict=True)
            loss = actor_critic_loss(lg[:, 0], v[:, 0], actions[sl, s], rewards[sl, s],
                                     float(v_next[0, 0]), LOSS).total
            ref_total = ref_total + loss
            if j < k - 1:
                theta = sgd_step(theta, loss, alpha, create_graph=True)
    ref = torch.autograd.grad(ref_total, list(model.parameters()))
    for a, r in zip(got, ref, strict=True):
        torch.testing.assert_close(a, r, atol=TOL, rtol=TOL)
    if kind == "cnn":  # the previous views reach the CNN's gradient: zero-filled differs
        names = [nm for nm, _ in model.named_parameters()]
        assert float(got[names.index("prev_embed.weight")].abs().max()) > 0
