"""The maths of ISAR and SAVN: meta-gradients vs finite differences (float64), the
update schedule of a 70-step ISAR episode, first order, and recompute vs per-step graph.

The workers run on a scripted environment whose observations are fixed feature
vectors, so the network is tiny and float64. L_AC uses returns and advantages from
detached values; the finite-difference reference therefore holds them fixed at their
values at phi_0 (which is what autograd differentiates), and recomputes everything
else (per-step forwards, inner SGD steps) independently of the implementation.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from geonav.policy.config import LossConfig, NetConfig
from geonav.policy.isar import ISARWorker
from geonav.policy.losses import returns_and_advantages
from geonav.policy.meta_config import ISARConfig, SAVNConfig
from geonav.policy.model import ActorCritic
from geonav.policy.optim import SharedAdam
from geonav.policy.savn import InteractionLoss, SAVNWorker

FDIM = 32
@pytest.fixture(autouse=True)
def float64():
    """Everything in float64 (the network's zero initial state included)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


NET = NetConfig(encoder="random", obs_size_px=20, embed_dim=4, action_embed_dim=3,
                hidden_size=6, lstm_size=5)


class ScriptedEnv:
    """Observations: fixed float64 feature vectors per step; -0.01 per step, +5 and
    terminated at ``success_at`` (None: never), truncated at ``max_steps``."""

    def __init__(self, max_steps: int, success_at: int | None, seed: int = 0) -> None:
        g = np.random.default_rng(seed)
        self.feats = g.normal(size=(max_steps + 1, FDIM))
        self.target = g.normal(size=FDIM)
        self.max_steps, self.success_at = max_steps, success_at
        self.actions: list[int] = []
        self.unwrapped = self
        self.np_random = np.random.default_rng(0)

    def _obs(self):
        return {"image": self.feats[self.t].copy(), "target": self.target.copy()}

    def _info(self, success=False):
        return {"shortest_path": 1, "collided": False, "success": success, "task": "s",
                "task_index": 0, "cell": (0, 0), "target_cell": (1, 1), "alt_m": 75.0}

    def reset(self, *, seed=None, options=None):
        self.t = 0
        self.actions = []
        return self._obs(), self._info()

    def step(self, a):
        self.t += 1
        self.actions.append(int(a))
        term = self.success_at is not None and self.t == self.success_at
        trunc = not term and self.t >= self.max_steps
        return self._obs(), (5.0 if term else -0.01), term, trunc, self._info(term)


def tiny_model(seed: int = 0) -> ActorCritic:
    torch.manual_seed(seed)
    m = ActorCritic(NET).double()
    with torch.no_grad():  # larger actor/critic weights than SAVN's init: non-trivial maths
        m.actor.weight.normal_(0, 0.5)
        m.critic.weight.normal_(0, 0.5)
        # non-zero biases: with zero ones the first step's previous-action embedding sits
        # exactly on the ReLU kink, where the inner gradient (ReLU' steps) jumps and the
        # finite differences of the meta-objective are meaningless
        for name, p in m.named_parameters():
            if name.endswith("bias"):
                p.normal_(0, 0.3)
    return m


def capture(worker):
    grads = []
    worker.on_gradients = lambda gs: grads.append([g.detach().clone() for g in gs])
    return grads


def flat(ts):
    return torch.cat([t.reshape(-1) for t in ts])


# -- reference implementation ---------------------------------------------------------------
def step_forward(model, params, x, target, state):
    logits, v, state = torch.func.functional_call(
        model, params, (x[None, None], target[None], state))
    return logits[0, 0], v[0, 0], state


def fixed_terms(rewards, values, bootstrap, cfg):
    return returns_and_advantages(rewards, values.detach(), bootstrap, cfg.gamma, cfg.tau)


def ac_loss_fixed(logits, values, actions, R, A, cfg):
    logp = F.log_softmax(logits, -1)
    ent = -(logp.exp() * logp).sum(-1)
    pol = (-logp[torch.arange(len(actions)), torch.tensor(actions)] * A - cfg.beta * ent).sum()
    return pol + cfg.value_coef * (0.5 * (R - values).pow(2)).sum()


def isar_window_ref(model, phi, env, n, alpha, cfg, fixed=None, create_graph=True):
    """sum_k L_k of one window (the whole episode); ``fixed``: per-segment (R, A); when
    None they are computed here and returned (at this phi)."""
    names = list(phi)
    theta = dict(phi)
    state = model.initial_state()
    state = tuple(s.double() for s in state)
    target = torch.from_numpy(env.target)
    T = len(env.actions)
    segs = [list(range(s, min(s + n, T))) for s in range(0, T, n)]
    total, out_fixed = 0.0, []
    for k, idx in enumerate(segs):
        lg, vs = [], []
        for t in idx:
            logit, v, state = step_forward(model, theta, torch.from_numpy(env.feats[t]), target,
                                           state)
            lg.append(logit)
            vs.append(v)
        lg, vs = torch.stack(lg), torch.stack(vs)
        acts = [env.actions[t] for t in idx]
        rews = [-0.01] * len(idx)
        last = k == len(segs) - 1
        if last and env.success_at == T:
            rews[-1] = 5.0
        if fixed is None:
            if last:
                boot = 0.0
            else:
                _, vn, _ = step_forward(model, theta, torch.from_numpy(env.feats[idx[-1] + 1]),
                                        target, state)
                boot = float(vn.detach())
            out_fixed.append(fixed_terms(rews, vs, boot, cfg))
        R, A = (fixed or out_fixed)[k]
        L = ac_loss_fixed(lg, vs, acts, R.double(), A.double(), cfg)
        total = total + L
        if not last:
            gs = torch.autograd.grad(L, [theta[m] for m in names], create_graph=create_graph,
                                     retain_graph=True)
            theta = {m: theta[m] - alpha * g for m, g in zip(names, gs, strict=False)}
    return total, out_fixed


def fd_check(fun, phi, grad, n_dirs=3, eps=1e-6, seed=0):
    """Central differences of ``fun`` along random directions vs ``grad``."""
    g = torch.Generator().manual_seed(seed)
    errs = []
    for _ in range(n_dirs):
        d = {k: torch.randn(v.shape, generator=g, dtype=v.dtype) for k, v in phi.items()}
        with torch.enable_grad():
            fp = float(fun({k: (v.detach() + eps * d[k]).requires_grad_(True)
                            for k, v in phi.items()}))
            fm = float(fun({k: (v.detach() - eps * d[k]).requires_grad_(True)
                            for k, v in phi.items()}))
        fd = (fp - fm) / (2 * eps)
        an = float(sum((grad[k] * d[k]).sum() for k in phi))
        errs.append((fd, an))
    return errs


def run_isar(second_order=True, path="recompute", success_at=15, max_steps=70, alpha=0.3):
    model = tiny_model()
    env = ScriptedEnv(max_steps, success_at)
    cfg = ISARConfig(n_steps=5, k_segments=3, alpha=alpha, second_order=second_order,
                     gradient_path=path, lr=1e-3, workers=0, max_grad_norm=0.0)
    opt = torch.optim.SGD(model.parameters(), lr=0.0)
    w = ISARWorker(0, model, opt, env, cfg, None, seed=3)
    grads = capture(w)
    phi0 = {k: v.detach().clone() for k, v in model.named_parameters()}
    w.run_episode(1)
    return model, env, cfg, grads, phi0


def test_isar_window_meta_gradient_matches_finite_differences():
    model, env, cfg, grads, phi0 = run_isar(second_order=True)
    assert len(grads) == 1 and len(env.actions) == 15      # one window of K = 3 segments
    names = list(phi0)
    impl = dict(zip(names, grads[0], strict=False))
    leaves = {k: v.clone().requires_grad_(True) for k, v in phi0.items()}
    _, fixed = isar_window_ref(model, leaves, env, 5, cfg.alpha, cfg.loss)
    fun = lambda p: isar_window_ref(model, p, env, 5, cfg.alpha, cfg.loss, fixed,  # noqa: E731
                                    create_graph=False)[0]
    for fd, an in fd_check(fun, {k: v.clone().requires_grad_(True) for k, v in phi0.items()},
                           impl):
        assert an == pytest.approx(fd, rel=1e-5, abs=1e-8)
    # the first-order gradient is measurably different: the check above can fail
    _, env1, _, g1, _ = run_isar(second_order=False)
    assert env1.actions == env.actions
    assert (flat(g1[0]) - flat(grads[0])).norm() > 1e-3 * flat(grads[0]).norm()


def test_first_order_is_the_sum_of_segment_gradients():
    model, env, cfg, grads, phi0 = run_isar(second_order=False)
    names = list(phi0)
    leaves = {k: v.clone().requires_grad_(True) for k, v in phi0.items()}
    _, fixed = isar_window_ref(model, leaves, env, 5, cfg.alpha, cfg.loss)
    # theta_k = phi + c_k with c_k constant: each L_k differentiated at its own theta_k
    total, _ = isar_window_ref(model, leaves, env, 5, cfg.alpha, cfg.loss, fixed,
                               create_graph=False)
    ref = torch.autograd.grad(total, [leaves[k] for k in names])
    assert torch.allclose(flat(grads[0]), flat(ref), rtol=1e-9, atol=1e-12)


def test_recompute_equals_per_step_graph():
    for order in (True, False):
        _, env_a, _, ga, _ = run_isar(second_order=order, path="recompute", success_at=None)
        _, env_b, _, gb, _ = run_isar(second_order=order, path="per-step", success_at=None)
        assert env_a.actions == env_b.actions and len(ga) == len(gb) == 5
        for a, b in zip(ga, gb, strict=False):
            assert torch.allclose(flat(a), flat(b), rtol=1e-9, atol=1e-12)


def test_isar_70_step_episode_schedule_and_theta_reset():
    model = tiny_model()
    shared = tiny_model()
    shared.load_state_dict(model.state_dict())
    env = ScriptedEnv(70, None)
    cfg = ISARConfig(alpha=0.3, lr=1e-2, workers=0, fused=False)
    opt = SharedAdam(shared.parameters(), lr=1e-2, fused=False)
    after_step: list[list[torch.Tensor]] = []
    orig = opt.step

    def step(*a, **k):
        out = orig(*a, **k)
        after_step.append([p.detach().clone() for p in shared.parameters()])
        return out

    opt.step = step
    w = ISARWorker(0, model, opt, env, cfg, None, seed=1, shared_model=shared)
    w.events, w.theta_log = [], []
    before = [p.detach().clone() for p in shared.parameters()]
    rec = w.run_episode(1)
    assert rec["length"] == 70 and not rec["success"]
    inner = [e[1] for e in w.events if e[0] == "inner"]
    adapt = [(e[1], e[2]) for e in w.events if e[0] == "adapt"]
    assert inner == [5, 10, 20, 25, 35, 40, 50, 55, 65]
    assert adapt == [(15, 3), (30, 3), (45, 3), (60, 3), (70, 2)]  # partial window flushed
    assert rec["inner_updates"] == 9 and rec["adaptive_updates"] == 5
    assert len(after_step) == 5
    names = [n for n, _ in shared.named_parameters()]
    for theta, phi in zip(w.theta_log, after_step, strict=False):
        assert all(torch.equal(theta[n], p) for n, p in zip(names, phi, strict=False))
    assert not all(torch.equal(a, b) for a, b in zip(before, after_step[0], strict=False))


# -- SAVN ----------------------------------------------------------------------------------
def savn_ref(model, tcn, phi, lam_params, env, k, alpha, cfg, fixed=None, create_graph=True):
    names = list(phi)
    theta = dict(phi)
    state = tuple(s.double() for s in model.initial_state())
    target = torch.from_numpy(env.target)
    T = len(env.actions)
    lg_all, v_all = [], []
    for s in range(0, T, k):
        idx = list(range(s, min(s + k, T)))
        hs, lg = [], []
        for t in idx:
            logit, v, state = step_forward(model, theta, torch.from_numpy(env.feats[t]), target,
                                           state)
            hs.append(state[0][0])
            lg.append(logit)
            v_all.append(v)
        lg_all += lg
        if idx[-1] == T - 1:
            break
        rows = torch.cat([torch.stack(hs), F.softmax(torch.stack(lg), -1)], -1)
        l_int = torch.func.functional_call(tcn, lam_params, (rows,))
        gs = torch.autograd.grad(l_int, [theta[m] for m in names], create_graph=create_graph,
                                 retain_graph=True, allow_unused=True)
        theta = {m: theta[m] if g is None else theta[m] - alpha * g
                 for m, g in zip(names, gs, strict=True)}
    lg, vs = torch.stack(lg_all), torch.stack(v_all)
    rews = [-0.01] * T
    if env.success_at == T:
        rews[-1] = 5.0
    if fixed is None:
        fixed = fixed_terms(rews, vs, 0.0, cfg)
    R, A = fixed
    return ac_loss_fixed(lg, vs, env.actions, R.double(), A.double(), cfg), fixed


def test_savn_episode_meta_gradient_matches_finite_differences():
    model = tiny_model()
    torch.manual_seed(5)
    tcn = InteractionLoss(4, 3).double()
    env = ScriptedEnv(30, success_at=10)
    cfg = SAVNConfig(k_steps=4, inner_steps=-1, inner_lr=0.3, workers=0)
    opt = torch.optim.SGD(list(model.parameters()) + list(tcn.parameters()), lr=0.0)
    w = SAVNWorker(0, model, opt, env, cfg, None, seed=2, tcn=tcn)
    grads = capture(w)
    rec = w.run_episode(1)
    assert rec["length"] == 10 and rec["inner_updates"] == 2 and len(grads) == 1
    pnames = [n for n, _ in model.named_parameters()]
    lnames = [n for n, _ in tcn.named_parameters()]
    impl = {**{("P", n): g for n, g in zip(pnames, grads[0][:len(pnames)], strict=False)},
            **{("L", n): g for n, g in zip(lnames, grads[0][len(pnames):], strict=False)}}
    assert flat([impl[("L", n)] for n in lnames]).norm() > 0  # Lambda learns (2nd order)
    p0 = {("P", n): v.detach().clone() for n, v in model.named_parameters()}
    p0.update({("L", n): v.detach().clone() for n, v in tcn.named_parameters()})

    def split(p):
        return ({n: p[("P", n)] for n in pnames}, {n: p[("L", n)] for n in lnames})

    leaves = {k: v.clone().requires_grad_(True) for k, v in p0.items()}
    _, fixed = savn_ref(model, tcn, *split(leaves), env, 4, cfg.inner_lr, cfg.loss)
    fun = lambda p: savn_ref(model, tcn, *split(p), env, 4, cfg.inner_lr, cfg.loss,  # noqa
                             fixed, create_graph=True)[0]
    for fd, an in fd_check(fun, p0, impl):
        assert an == pytest.approx(fd, rel=1e-5, abs=1e-8)


def test_savn_presets_and_gradient_limit():
    from geonav.policy.meta_config import base_config

    pub = base_config("savn", {"preset": "savn-published"})
    ali = base_config("savn", {"preset": "savn-aligned"})
    assert (pub.k_steps, pub.inner_steps) == (6, 4) and (ali.k_steps, ali.inner_steps) == (5, -1)
    for cfg, want in ((pub, 4), (ali, 13)):
        model, tcn = tiny_model(), InteractionLoss(cfg.k_steps).double()
        opt = torch.optim.SGD(list(model.parameters()) + list(tcn.parameters()), lr=0.0)
        w = SAVNWorker(0, model, opt, ScriptedEnv(70, None), cfg, None, seed=0, tcn=tcn)
        assert w.run_episode(1)["inner_updates"] == want


def test_teacher_kl_is_added_with_its_weight():
    from geonav.policy.functional import Segment, segment_loss, teacher_kl

    model = tiny_model()
    g = torch.Generator().manual_seed(0)
    seg = Segment(tuple(s.double() for s in model.initial_state()),
                  torch.randn(FDIM, generator=g, dtype=torch.float64))
    for t in range(4):
        seg.views.append(torch.randn(FDIM, generator=g, dtype=torch.float64))
        seg.actions.append(t % 4)
        seg.rewards.append(-0.01)
        seg.teacher_logp.append(torch.log_softmax(torch.randn(4, generator=g,
                                                              dtype=torch.float64), -1))
    base = segment_loss(model, None, seg, 0.0, LossConfig())
    half = segment_loss(model, None, seg, 0.0, LossConfig(), kl_weight=0.5)
    kl = teacher_kl(torch.stack(seg.teacher_logp), base.logits)
    assert float(kl) > 0
    assert float(half.loss - base.loss) == pytest.approx(0.5 * float(kl), rel=1e-12)


def test_grads_of_gives_each_gradient_its_leafs_layout():
    """The learned loss's first convolution gets a gradient with other strides than its
    weight from ``autograd.grad``; torch's fused Adam steps a parameter with its gradient
    in memory order, so the SAVN worker's step took the wrong elements until grads_of
    returned the leaf's layout. Fused and unfused Adam now agree."""
    from geonav.policy.functional import grads_of

    def meta_loss(mod):  # Lambda's gradient through an inner step, as SAVN's
        rows = torch.randn(3, 20, generator=torch.Generator().manual_seed(0),
                           requires_grad=True)
        (g,) = torch.autograd.grad(mod(rows), [rows], create_graph=True)
        return (g * torch.arange(60.0).view(3, 20)).sum()

    tcn = InteractionLoss(3, 10)
    w = tcn.ll_conv1.weight
    (raw,) = torch.autograd.grad(meta_loss(tcn), [w])
    assert raw.stride() != w.stride()  # what the fix is for (torch 2.13, CPU)
    steps = []
    for fused in (True, False):
        mod = InteractionLoss(3, 10)
        mod.load_state_dict(tcn.state_dict())
        params = list(mod.parameters())
        opt = torch.optim.Adam(params, lr=0.05, fused=fused)
        for p, g in zip(params, grads_of(meta_loss(mod), params), strict=True):
            assert g.stride() == p.stride()
            p.grad = g
        opt.step()
        steps.append([p.detach().clone() for p in params])
    for a, b in zip(*steps, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)
