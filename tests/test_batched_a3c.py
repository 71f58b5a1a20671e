"""Batched A3C: the reference worker's update at B = 1, learning, resume, device checks."""

import pytest
import torch
from batched_helpers import assert_grads_close, first_update_grads, greedy_sr, random_sr

from geonav.errors import ConfigError
from geonav.policy.a3c import A3CTrainer
from geonav.policy.batched.trainer import BatchedA3CTrainer, resolve_device
from geonav.policy.callbacks import read_metrics
from geonav.policy.checkpoint import load_checkpoint
from geonav.policy.config import A3CConfig
from geonav.policy.testing import tiny_env_factory, tiny_net


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_b1_first_update_equals_reference_worker(encoder):
    """Same seeds, B = 1: the same trajectory, and the same gradient of the first update."""
    factory = tiny_env_factory(cells=5, max_steps=12)
    net = tiny_net(encoder, 32, size=16)
    cfg = A3CConfig(episodes=1, workers=0, t_max=3, seed=4)
    ref = A3CTrainer(factory, net, cfg, tensorboard=False)
    bat = BatchedA3CTrainer(factory, net, cfg, batch=1, tensorboard=False)
    ref_grads, got, rec, _, _ = first_update_grads(ref, bat)
    assert rec["length"] > cfg.t_max  # the first rollout lies inside the first episode
    names = [n for n, _ in ref.model.named_parameters()]
    assert_grads_close(names, ref_grads, got, 2e-6, 1e-5)


def test_learns_tiny_task_and_resumes(tmp_path):
    # max_steps 7: a fixed action distribution (image-blind) rarely succeeds (issue 10);
    # Adam eps 1e-5 without AMSGrad (the defaults, 1e-3 / AMSGrad, learn far slower here).
    factory = tiny_env_factory(cells=4, max_steps=7)
    env = factory()
    net = tiny_net("random", 32)
    cfg = A3CConfig(episodes=3000, lr=1e-3, adam_eps=1e-5, amsgrad=False, seed=0,
                    checkpoint_every=1500)
    t = BatchedA3CTrainer(factory, net, cfg, batch=16, out_dir=tmp_path / "run",
                          tensorboard=False)
    res = t.train()
    assert res.episodes == 3000
    rows = read_metrics(tmp_path / "run" / "metrics.csv")
    assert len(rows) == 3000 and rows[-1]["episode"] == 3000
    assert set(rows[0]) >= {"policy_loss", "value_loss", "entropy", "spl", "success"}
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert sr >= rnd + 0.3, (sr, rnd)
    ck = load_checkpoint(tmp_path / "run" / "checkpoints" / "final.pt")
    assert ck.episodes == 3000 and ck.rng["engine"] == "batched"
    # resume: continues from the checkpoint to a larger budget
    t2 = BatchedA3CTrainer(factory, None, A3CConfig(**{**cfg.__dict__, "episodes": 3040}),
                           batch=16, out_dir=tmp_path / "run",
                           resume=tmp_path / "run" / "checkpoints" / "latest.pt",
                           tensorboard=False)
    for k, v in ck.model_state.items():
        torch.testing.assert_close(t2.model.state_dict()[k].cpu(), v)
    assert t2.train().episodes == 3040
    assert len(read_metrics(tmp_path / "run" / "metrics.csv")) == 3040


def test_device_checks():
    assert resolve_device("cpu").type == "cpu"
    with pytest.raises(ConfigError):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no GPU"):
            resolve_device("cuda")


def test_lr_warmup_ramps_the_rate_and_continues_after_resume(tmp_path):
    """lr_warmup = 4: the k-th optimiser step (k = 1, 2, ...) runs at lr * min(1, k / 4),
    read from the optimiser's own step count, so a resumed run continues its ramp."""
    from geonav.policy.optim import warm_up_lr

    p = torch.nn.Parameter(torch.zeros(3))
    opt = torch.optim.Adam([p], lr=1.0)
    seen = []
    for _ in range(6):
        p.grad = torch.ones(3)
        warm_up_lr(opt, 0.1, 4)
        seen.append(opt.param_groups[0]["lr"])
        opt.step()
    assert seen == pytest.approx([0.025, 0.05, 0.075, 0.1, 0.1, 0.1])
    resumed = torch.optim.Adam([p], lr=1.0)
    resumed.load_state_dict(opt.state_dict())
    warm_up_lr(resumed, 0.1, 10)
    assert resumed.param_groups[0]["lr"] == pytest.approx(0.07)  # step 7 of a 10-step ramp

    factory = tiny_env_factory(cells=4, max_steps=7)
    net = tiny_net("random", 32)
    moved = {}
    for warm in (0, 1000):
        cfg = A3CConfig(episodes=4, workers=0, t_max=3, seed=1, lr=1e-3, lr_warmup=warm)
        tr = BatchedA3CTrainer(factory, net, cfg, batch=2, tensorboard=False)
        before = [q.detach().clone() for q in tr.params_list]
        tr.train()
        moved[warm] = sum(float((q.detach() - b).abs().sum())
                          for q, b in zip(tr.params_list, before, strict=True))
    assert 0 < moved[1000] < 0.1 * moved[0]
    with pytest.raises(ConfigError, match="lr_warmup"):
        A3CConfig(lr_warmup=-1)


@pytest.mark.parametrize("engine", ["batched", "async"])
def test_a_diverged_run_stops_with_a_clear_error(tmp_path, engine):
    """NaN losses end the run at once with TrainingDiverged, naming the episode, after the
    metrics CSV has its row (a diverged meta-SAVN run used to train on as NaN and then die
    in the next evaluation's sampling with "probability tensor contains nan")."""
    from geonav.errors import TrainingDiverged

    factory = tiny_env_factory(cells=4, max_steps=7)
    net = tiny_net("random", 32)
    cfg = A3CConfig(episodes=40, workers=0, seed=0, eval_every=20)
    out = tmp_path / engine
    if engine == "batched":
        t = BatchedA3CTrainer(factory, net, cfg, batch=4, out_dir=out, tensorboard=False)
        params = t.params_list
    else:
        t = A3CTrainer(factory, net, cfg, out_dir=out, tensorboard=False)
        params = list(t.model.parameters())
    with torch.no_grad():
        params[-1].fill_(float("nan"))  # the last layer: every loss of the episode is NaN
    with pytest.raises(TrainingDiverged, match=r"diverged at episode 1\b.*value_loss = nan"):
        t.train()
    rows = read_metrics(out / "metrics.csv")
    assert rows and rows[0]["episode"] == 1


def test_finite_losses_pass_the_check():
    from geonav.policy.a3c import check_finite_losses

    check_finite_losses({"episode": 3, "policy_loss": -0.2, "value_loss": 1e30, "entropy": 1.3})
    check_finite_losses({"episode": 3})  # records without losses (nothing to judge)


def prev_view_case(encoder, cells=5):
    """A network with the extra input slot, the tiny lattice and its views at 90 m."""
    from dataclasses import replace

    from geonav.policy.teacher import PrevViewSpec

    px = 20 if encoder == "cnn" else 32
    net = replace(tiny_net(encoder, px, size=16), prev_view_input=True)
    factory = tiny_env_factory(cells=cells, max_steps=12, obs_size_px=px)
    spec = PrevViewSpec(tiny_env_factory(cells=cells, max_steps=12, alt_m=90.0,
                                         obs_size_px=px), 90.0)
    return net, factory, spec


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_b1_previous_view_input_equals_reference(float64_default, encoder):
    """The curriculum's option B on batched A3C, B = 1, float64, 1e-10. The async A3C
    worker has no extra input; the reference is the async ISAR worker with windows of one
    t_max-step segment (K = 1: no inner step, one Adam step per segment, the A3C worker's
    update; checked here without the input too), over every rollout of its first episode.
    Zero-filling the slot instead changes the gradients (the input matters)."""
    from geonav.policy.isar import ISARTrainer
    from geonav.policy.meta_config import ISARConfig

    net, factory, spec = prev_view_case(encoder)
    cfg = A3CConfig(episodes=1, workers=0, t_max=3, seed=4)
    ref_cfg = ISARConfig(episodes=1, workers=0, n_steps=3, k_segments=1, seed=4)
    names = None
    grads = {}
    for prev in (spec, None):
        ref = ISARTrainer(factory, net, ref_cfg, prev_view=prev, tensorboard=False)
        worker = ref.inline_worker()
        ref_grads, got = [], []
        worker.on_gradients = lambda gs, out=ref_grads: out.append([g.clone() for g in gs])
        rec = worker.run_episode(1)
        n = rec["length"] // cfg.t_max  # the rollouts inside the first episode
        assert n >= 2
        bat = BatchedA3CTrainer(factory, net, cfg, prev_view=prev, batch=1,
                                tensorboard=False)
        bat._setup()
        bat.on_gradients = lambda gs, out=got: out.append([g.clone() for g in gs])
        for _ in range(n):
            bat.update()
        names = [k for k, _ in ref.model.named_parameters()]
        assert got[0][0].dtype == torch.float64
        for a, b in zip(ref_grads[:n], got, strict=True):
            assert_grads_close(names, a, b, 1e-10, 1e-10)
        grads[prev is None] = got
    i = names.index("prev_embed.weight")
    assert float((grads[False][0][i] - grads[True][0][i]).abs().max()) > 1e-6


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_previous_view_input_at_b3_equals_batched_isar_with_one_segment(float64_default,
                                                                         encoder):
    """B = 3 slots whose episodes end at different steps (new ones start mid-rollout):
    batched A3C with the input equals batched ISAR with K = 1 (whose input is tested
    against the async worker) update by update, float64, 1e-10."""
    from geonav.policy.batched.isar import BatchedISARTrainer
    from geonav.policy.meta_config import ISARConfig

    net, factory, spec = prev_view_case(encoder, cells=3)
    a3c = BatchedA3CTrainer(factory, net, A3CConfig(episodes=9, workers=0, t_max=5, seed=2),
                            prev_view=spec, batch=3, tensorboard=False)
    isar = BatchedISARTrainer(factory, net, ISARConfig(episodes=9, workers=0, n_steps=5,
                                                       k_segments=1, seed=2),
                              prev_view=spec, batch=3, tensorboard=False)
    seen = {}
    for name, t in (("a3c", a3c), ("isar", isar)):
        t._setup()
        seen[name] = []
        t.on_gradients = lambda gs, out=seen[name]: out.append([g.clone() for g in gs])
        ends = []
        for _ in range(6):
            ends += [(f["slot"], f["length"]) for f in t.update()[0]]
        seen[name + "-ends"] = ends
    assert seen["a3c-ends"] == seen["isar-ends"]
    assert len({length for _, length in seen["a3c-ends"]}) > 1  # out of step
    names = [k for k, _ in a3c.model.named_parameters()]
    for a, b in zip(seen["isar"], seen["a3c"], strict=True):
        assert_grads_close(names, a, b, 1e-10, 1e-10)
