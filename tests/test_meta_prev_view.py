"""The curriculum's option B: the extra input slot E(o^prev) (ALGORITHMS.md (e))."""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import pytest
import torch

from geonav.convergence import ConvergenceCriterion
from geonav.errors import ConfigError
from geonav.policy.a3c import train_a3c
from geonav.policy.checkpoint import load_checkpoint
from geonav.policy.config import A3CConfig, NetConfig
from geonav.policy.encoders import build_frozen_encoder
from geonav.policy.inference import PolicyRunner
from geonav.policy.meta_config import CurriculumConfig, ISARConfig
from geonav.policy.model import ActorCritic, param_dict
from geonav.policy.testing import tiny_env_factory, tiny_net
from geonav.testing import textured_scene, tiny_taskset

# The parameters of ActorCritic before the slot existed (tiny_net: random encoder F=128,
# E=64, A=10, H=64).
ORIGINAL = {
    "obs_embed.weight": (64, 128), "obs_embed.bias": (64,),
    "target_embed.weight": (64, 128), "target_embed.bias": (64,),
    "action_embed.weight": (10, 4), "action_embed.bias": (10,),
    "fc.weight": (64, 2 * 64 + 10), "fc.bias": (64,),
    "lstm.weight_ih": (256, 64), "lstm.weight_hh": (256, 64),
    "lstm.bias_ih": (256,), "lstm.bias_hh": (256,),
    "actor.weight": (4, 64), "actor.bias": (4,),
    "critic.weight": (1, 64), "critic.bias": (1,),
}


def slot_net(encoder: str = "random") -> NetConfig:
    return dataclasses.replace(tiny_net(encoder), prev_view_input=True)


def inputs(model: ActorCritic, T: int = 4, B: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    n = model.cfg.obs_size_px
    if model.takes_images:
        def img(*s):
            return torch.randint(0, 256, (*s, n, n, 3), generator=g, dtype=torch.uint8)
    else:
        fdim = model.obs_embed.in_features

        def img(*s):
            return torch.rand(*s, fdim, generator=g)
    return img(T, B), img(B), model.initial_state(B), img(T, B)


def test_flag_off_keeps_the_original_parameters():
    names = {k: tuple(v.shape) for k, v in ActorCritic(tiny_net()).named_parameters()}
    assert names == ORIGINAL
    cnn = dict(ActorCritic(tiny_net("cnn")).named_parameters())
    assert "prev_embed.weight" not in cnn and cnn["fc.weight"].shape == (64, 2 * 64 + 10)
    assert NetConfig().prev_view_input is False
    model = ActorCritic(tiny_net())
    obs, tgt, st, prev = inputs(model)
    with pytest.raises(ValueError, match="no previous-view slot"):
        model(obs, tgt, st, prev)


def test_flag_on_adds_one_embedding_before_the_fc():
    names = {k: tuple(v.shape) for k, v in ActorCritic(slot_net()).named_parameters()}
    extra = {"prev_embed.weight": (64, 128), "prev_embed.bias": (64,),
             "fc.weight": (64, 3 * 64 + 10)}
    assert names == {**ORIGINAL, **extra}


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_functional_and_module_forward_agree_and_none_zero_fills(encoder):
    torch.manual_seed(0)
    model = ActorCritic(slot_net(encoder))
    with torch.no_grad():  # non-zero biases: a zero-filled slot still contributes ReLU(b)
        model.prev_embed.bias.uniform_(-0.5, 0.5)
    obs, tgt, st, prev = inputs(model)
    for p in (prev, None):
        args = (obs, tgt, st) if p is None else (obs, tgt, st, p)
        lm, vm, (hm, cm, pm) = model(*args)
        lf, vf, (hf, cf, pf) = torch.func.functional_call(model, param_dict(model), args,
                                                          strict=True)
        for a, b in ((lm, lf), (vm, vf), (hm, hf), (cm, cf), (pm, pf)):
            assert torch.equal(a, b)
    # stage 0: no prev -> the same numbers as feeding zero features to the slot
    zeros = torch.zeros(obs.shape[0], obs.shape[1], model.prev_embed.in_features)
    l0, v0, s0 = model(obs, tgt, st)
    lz, vz, sz = model(obs, tgt, st, zeros)
    assert torch.equal(l0, lz) and torch.equal(v0, vz) and torch.equal(s0[0], sz[0])
    lp, _, _ = model(obs, tgt, st, prev)  # and the slot is used
    assert not torch.allclose(lp, l0)
    # T one-step calls give the sequence call's numbers
    s = st
    steps = []
    for t in range(obs.shape[0]):
        lg, _, s = model(obs[t:t + 1], tgt, s, prev[t:t + 1])
        steps.append(lg[0])
    assert torch.allclose(torch.stack(steps), lp, atol=1e-6)


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("pv")
    scene = textured_scene(size_m=300.0)
    scene.save(root / "scene")
    tiny_taskset(scene, cells=4, max_steps=20).save(root / "tasks.json")
    return root


@pytest.fixture(scope="module")
def factory(scene_files):
    from geonav.policy.cli import EnvFactory

    return EnvFactory(str(scene_files / "scene"), str(scene_files / "tasks.json"),
                      obs_size_px=32)


HARD = ConvergenceCriterion(window=50, threshold=1.0, hold=1.0)  # runs the whole budget


def test_two_stage_input_curriculum_feeds_the_previous_altitude_view(factory, tmp_path,
                                                                     monkeypatch):
    from geonav.policy import isar, teacher
    from geonav.policy.curriculum import run_curriculum

    log: list[tuple[str, object]] = []
    orig_train, orig_forward = isar.ISARTrainer.train, ActorCritic.forward
    orig_view = teacher.PrevViewSource.view

    def train(self):
        log.append(("stage", self.env_factory.alt_m))
        return orig_train(self)

    def forward(self, obs, target, state, prev=None):
        log.append(("forward", None if prev is None else prev.detach().clone()))
        return orig_forward(self, obs, target, state, prev)

    def view(self, info):
        out = orig_view(self, info)
        log.append(("view", (int(info["task_index"]), tuple(int(c) for c in info["cell"]),
                             out.clone())))
        return out

    monkeypatch.setattr(isar.ISARTrainer, "train", train)
    monkeypatch.setattr(ActorCritic, "forward", forward)
    monkeypatch.setattr(teacher.PrevViewSource, "view", view)
    # eval_every=0: evaluation (geonav.policy.evaluation) zero-fills the slot, a known
    # limitation; this test checks what training feeds it.
    res = run_curriculum(factory, None, "isar", ISARConfig(workers=0, seed=0, eval_every=0),
                         CurriculumConfig(levels_m=(75.0, 45.0), stage_episodes=2,
                                          max_steps=12, teacher="input"),
                         out_dir=tmp_path, criterion=HARD, net_cfg=slot_net(),
                         engine="async")  # instruments the async ISAR worker
    assert [(s.alt_m, s.teacher, s.prev_view_alt_m) for s in res.stages] == \
        [(75.0, None, None), (45.0, None, 75.0)]
    cut = log.index(("stage", 45.0))
    stage0, stage1 = log[:cut], log[cut:]
    # stage 0: every forward zero-fills the slot, and no previous view is rendered
    assert all(e[1] is None for e in stage0 if e[0] == "forward")
    assert not [e for e in stage0 if e[0] == "view"]
    # stage 1: the views are the frozen features of the render at the same cell at 75 m
    env75 = dataclasses.replace(factory, alt_m=75.0)()
    env45 = dataclasses.replace(factory, alt_m=45.0)()
    enc = build_frozen_encoder(slot_net())
    views = [e[1] for e in stage1 if e[0] == "view"]
    assert len(views) >= 2 * 2  # at least start + one step per episode
    for ti, cell, feat in views:
        want = enc.features(env75.unwrapped.observation_at(ti, cell))
        assert torch.allclose(feat, want, atol=1e-6)
        assert float(feat.abs().sum()) > 0
        assert not torch.allclose(feat, enc.features(env45.unwrapped.observation_at(ti, cell)))
    # ... and every forward of stage 1 (acting, recompute, bootstrap) receives them
    fwd = [e[1] for e in stage1 if e[0] == "forward"]
    assert fwd and all(p is not None for p in fwd)
    feats = torch.stack([f for _, _, f in views])
    for p in fwd:
        rows = p.reshape(-1, p.shape[-1])
        assert float(rows.abs().sum()) > 0
        for r in rows:
            assert bool(((feats - r).abs().amax(dim=1) < 1e-6).any())
    # the choice is recorded: config.json and the checkpoint's architecture
    cfg1 = json.loads((tmp_path / "stage_1_45m" / "config.json").read_text())
    assert cfg1["teacher"] == {"kind": "input", "prev_alt_m": 75.0}
    assert cfg1["net"]["prev_view_input"] is True
    assert load_checkpoint(res.checkpoint).net_config.prev_view_input is True
    state = json.loads((tmp_path / "curriculum.json").read_text())
    assert state["curriculum"]["teacher"] == "input"


@pytest.mark.parametrize("algo", ["savn", "isar-per-step"])
def test_savn_and_per_step_isar_stages_take_the_previous_view(factory, tmp_path, algo):
    from geonav.policy.curriculum import run_curriculum
    from geonav.policy.meta_config import SAVNConfig

    base = SAVNConfig(workers=0, seed=0, k_steps=5) if algo == "savn" else \
        ISARConfig(workers=0, seed=0, gradient_path="per-step")
    res = run_curriculum(factory, None, algo.split("-")[0], base,
                         CurriculumConfig(levels_m=(75.0, 45.0), stage_episodes=1,
                                          max_steps=12, teacher="input"),
                         out_dir=tmp_path, criterion=HARD, net_cfg=slot_net())
    assert [s.prev_view_alt_m for s in res.stages] == [None, 75.0]


def test_batched_a3c_stage_takes_the_previous_view(factory, tmp_path):
    from geonav.policy.curriculum import run_curriculum

    res = run_curriculum(factory, None, "a3c", A3CConfig(workers=0, seed=0, t_max=5),
                         CurriculumConfig(levels_m=(75.0, 45.0), stage_episodes=2,
                                          max_steps=12, teacher="input"),
                         out_dir=tmp_path, criterion=HARD, net_cfg=slot_net(), batch=2)
    assert [s.prev_view_alt_m for s in res.stages] == [None, 75.0]
    cfg1 = json.loads((tmp_path / "stage_1_45m" / "config.json").read_text())
    assert cfg1["engine"]["name"] == "batched"
    assert cfg1["teacher"] == {"kind": "input", "prev_alt_m": 75.0}


def test_input_teacher_refuses_a_network_without_the_slot(factory, tmp_path):
    from geonav.policy.curriculum import run_curriculum

    train_a3c(tiny_env_factory(max_steps=6), tiny_net(), A3CConfig(episodes=1, workers=0),
              out_dir=tmp_path / "init")
    init = str(tmp_path / "init" / "checkpoints" / "final.pt")
    cur = CurriculumConfig(levels_m=(75.0, 45.0), stage_episodes=1, teacher="input")
    with pytest.raises(ConfigError, match="prev_view_input = true"):
        run_curriculum(factory, init, "isar", ISARConfig(workers=0), cur,
                       out_dir=tmp_path / "c1", criterion=HARD)
    assert not (tmp_path / "c1" / "stage_0_75m").exists()
    with pytest.raises(ConfigError, match="prev_view_input"):
        run_curriculum(factory, None, "isar", ISARConfig(workers=0), cur,
                       out_dir=tmp_path / "c2", criterion=HARD, net_cfg=tiny_net())
    with pytest.raises(ConfigError, match="a3c on engine = 'batched'"):
        run_curriculum(factory, None, "a3c", A3CConfig(workers=0), cur,
                       out_dir=tmp_path / "c3", criterion=HARD, net_cfg=slot_net(),
                       engine="async")
    from geonav.policy.isar import ISARTrainer
    from geonav.policy.teacher import PrevViewSpec

    with pytest.raises(ConfigError, match="extra input slot"):
        ISARTrainer(factory, tiny_net(), ISARConfig(workers=0),
                    prev_view=PrevViewSpec(factory, 75.0))


def test_cli_flag_sets_the_slot(factory):
    from geonav.policy.meta_cli import net_cfg_from_args

    on = net_cfg_from_args(argparse.Namespace(prev_view_input=True), {}, factory)
    assert on.prev_view_input is True
    assert net_cfg_from_args(argparse.Namespace(prev_view_input=None), {}, factory) is None


def test_policy_runner_zero_fills_the_slot(tmp_path):
    factory = tiny_env_factory(max_steps=8)
    train_a3c(factory, slot_net(), A3CConfig(episodes=2, workers=0, lr=1e-3), out_dir=tmp_path)
    path = tmp_path / "checkpoints" / "final.pt"
    ck = load_checkpoint(path)
    assert ck.meta["net"]["prev_view_input"] is True
    runner = PolicyRunner.from_checkpoint(path)
    assert runner.prev_view_input
    model, enc = ck.build_model(), ck.build_encoder()
    with torch.no_grad():  # make the zero-filled slot matter
        model.prev_embed.bias.uniform_(0.5, 1.0)
        runner.agent.model.prev_embed.bias.copy_(model.prev_embed.bias)
    env = factory()
    obs, _ = env.reset(seed=3)
    runner.reset()
    state = model.initial_state()
    tgt = enc.features(obs["target"])
    zeros = torch.zeros(1, 1, tgt.shape[-1])
    for _ in range(6):
        a = runner.act(obs["image"], obs["target"])
        with torch.no_grad():
            logits, _, state = model(enc.features(obs["image"])[None, None], tgt[None],
                                     state, zeros)
        assert a == int(torch.argmax(logits[0, 0]))
        obs, _, term, trunc, _ = env.step(a)
        if term or trunc:
            break
    img = np.zeros((32, 32, 3), np.uint8)
    assert runner.act(img, img, prev_image=img) in range(4)
    plain = tmp_path / "plain"
    train_a3c(factory, tiny_net(), A3CConfig(episodes=1, workers=0), out_dir=plain)
    r2 = PolicyRunner.from_checkpoint(plain / "checkpoints" / "final.pt")
    assert not r2.prev_view_input
    from geonav.errors import CheckpointError

    with pytest.raises(CheckpointError, match="no previous-view input slot"):
        r2.act(img, img, prev_image=img)
