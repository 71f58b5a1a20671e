"""ISAR and SAVN learn a tiny task; meta-training order and updates; curriculum stages."""

from __future__ import annotations

import dataclasses
import functools

import pytest
import torch

from geonav.camera import Camera
from geonav.convergence import ConvergenceCriterion
from geonav.env import GeoNavEnv
from geonav.errors import ConfigError
from geonav.policy.callbacks import Callback
from geonav.policy.encoders import build_frozen_encoder
from geonav.policy.evaluation import RandomAgent, eval_starts, evaluate
from geonav.policy.isar import train_isar
from geonav.policy.meta import MetaTrainer
from geonav.policy.meta_config import (
    CurriculumConfig,
    ISARConfig,
    MetaConfig,
    SAVNConfig,
    base_config,
    kl_weight,
)
from geonav.policy.savn import train_savn
from geonav.policy.testing import _scene, tiny_env_factory, tiny_net
from geonav.testing import textured_scene, tiny_taskset


@pytest.mark.parametrize("algo", ["isar", "savn"])
def test_learns_tiny_task_far_above_random(algo):
    factory = tiny_env_factory(cells=4, max_steps=10)
    env = factory()
    starts = eval_starts(env, 40, seed=1)
    random_sr = evaluate(RandomAgent(seed=1), env, starts=starts).success_rate
    if algo == "isar":
        res = train_isar(factory, tiny_net(), ISARConfig(episodes=150, workers=0, lr=1e-3,
                                                         alpha=1e-3, seed=0))
    else:
        res = train_savn(factory, tiny_net(), SAVNConfig(episodes=150, workers=0, lr=1e-3,
                                                         k_steps=5, inner_lr=1e-3, seed=0))
    learned = evaluate(res.model, env, frozen=build_frozen_encoder(res.model.cfg),
                       starts=starts, greedy=False, seed=1)
    assert random_sr < 0.45
    assert learned.success_rate >= random_sr + 0.35


def multi_task_factory(n=3, max_steps=12):
    scene = _scene(0)
    ts = tiny_taskset(scene, cells=4, max_steps=max_steps)
    cells = [(3, 3), (0, 0), (3, 0), (0, 3)][:n]
    tasks = [dataclasses.replace(ts.tasks[0], name=f"t{i}", target_cell=c)
             for i, c in enumerate(cells)]
    return functools.partial(GeoNavEnv, scene, dataclasses.replace(ts, tasks=tasks),
                             camera=Camera(32, 90.0))


@pytest.mark.parametrize("algo,workers", [("isar", 0), ("savn", 0), ("a3c", 0), ("isar", 2)])
def test_meta_training_order_and_one_update_per_batch(algo, workers):
    factory = multi_task_factory(3)
    meta = MetaConfig(episodes=7, workers=workers, batch_tasks=2, meta_lr=1e-2, seed=0)
    t = MetaTrainer(factory, tiny_net(), algo, base_config(algo, {}), meta,
                    keep_task_grads=True, mp_context="fork")
    res = t.train()
    assert [r["task_index"] for r in sorted(res.records, key=lambda r: r["episode"])] == \
        [0, 1, 2, 0, 1, 2, 0]
    assert [u["tasks"] for u in t.update_log] == [[0, 1], [2, 0], [1, 2], [0]]
    assert t.meta_updates == 4 and res.episodes == 7
    for u in t.update_log:  # psi <- psi - eta * sum_i g_i, exactly one step per batch
        total = [sum(g[j] for g in u["grads"]) for j in range(len(u["psi_before"]))]
        assert any(float(x.abs().sum()) > 0 for x in total)
        for before, after, g in zip(u["psi_before"], u["psi_after"], total, strict=False):
            assert torch.allclose(after, before - 1e-2 * g, atol=1e-7)
    # task gradients start from psi: the two tasks of a batch see the same parameters
    assert len(t.update_log[0]["grads"]) == 2


def test_meta_training_resumes_the_cyclic_order(tmp_path):
    factory = multi_task_factory(3)
    MetaTrainer(factory, tiny_net(), "a3c", base_config("a3c", {}),
                MetaConfig(episodes=4, workers=0, batch_tasks=2), out_dir=tmp_path).train()
    t = MetaTrainer(factory, tiny_net(), "a3c", base_config("a3c", {}),
                    MetaConfig(episodes=7, workers=0, batch_tasks=2), out_dir=tmp_path,
                    resume=tmp_path / "checkpoints" / "latest.pt")
    res = t.train()
    assert [r["task_index"] for r in res.records] == [1, 2, 0]
    assert [u["tasks"] for u in t.update_log] == [[1, 2], [0]]
    lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert len(lines) == 1 + 7


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("cur")
    scene = textured_scene(size_m=300.0)
    scene.save(root / "scene")
    tiny_taskset(scene, cells=4, max_steps=20).save(root / "tasks.json")
    return root


class KLs(Callback):
    def __init__(self):
        self.seen = []

    def on_episode(self, record):
        self.seen.append((record["episode"], record.get("kl_weight")))


def test_curriculum_advances_on_criterion_and_budget_and_decays_the_teacher(scene_files,
                                                                            tmp_path):
    from geonav.policy.cli import EnvFactory
    from geonav.policy.curriculum import run_curriculum

    f = EnvFactory(str(scene_files / "scene"), str(scene_files / "tasks.json"), obs_size_px=32)
    kls = KLs()
    easy = ConvergenceCriterion(window=2, threshold=0.5, hold=0.5)  # holds within the budget
    res = run_curriculum(f, None, "isar", ISARConfig(workers=0, seed=0),
                         CurriculumConfig(stage_episodes=8, max_steps=120,  # paper's reading
                                          teacher_mask="none", teacher_schedule="linear"),
                         out_dir=tmp_path / "a", criterion=easy, net_cfg=tiny_net(),
                         callbacks=[kls],
                         engine="async")  # lambda by record order: one worker's episodes
    assert [s.alt_m for s in res.stages] == [75.0, 45.0, 15.0]
    assert all(s.converged_at is not None and s.episodes < 8 for s in res.stages)
    assert res.stages[0].teacher is None
    assert res.stages[1].teacher == res.stages[0].checkpoint
    assert res.stages[2].teacher == res.stages[1].checkpoint
    # lambda: 1 -> 0 linearly over the first 25 % of the 8-episode budget (2 episodes)
    stage2 = [w for ep, w in kls.seen[res.stages[0].episodes:]][:3]
    assert stage2 == [1.0, 0.5, 0.0][:len(stage2)]
    assert [kl_weight(e, 100) for e in (1, 13, 26, 50)] == [1.0, 0.52, 0.0, 0.0]
    hard = ConvergenceCriterion(window=50, threshold=1.0, hold=1.0)  # cannot hold in 5
    res = run_curriculum(f, res.checkpoint, "isar", ISARConfig(workers=0, seed=0),
                         CurriculumConfig(levels_m=(45.0, 15.0), stage_episodes=5,
                                          teacher="none"),
                         out_dir=tmp_path / "b", criterion=hard)
    assert [(s.episodes, s.converged_at) for s in res.stages] == [(5, None), (5, None)]


def test_curriculum_keeps_the_task_sets_episode_cap_unless_told(scene_files, tmp_path,
                                                               monkeypatch):
    """CurriculumConfig.max_steps None (the default): every level runs with the task set's
    own cap (the env factory's); set, it overrides it."""
    import geonav.policy.engine as engine
    from geonav.policy.cli import EnvFactory
    from geonav.policy.curriculum import run_curriculum

    class Built(Exception):
        pass

    seen = []

    def fake_build_trainer(algo, eng, factory, *args, **kwargs):
        seen.append((factory.alt_m, factory.max_steps, factory().max_steps_of(0)))
        raise Built

    monkeypatch.setattr(engine, "build_trainer", fake_build_trainer)
    f = EnvFactory(str(scene_files / "scene"), str(scene_files / "tasks.json"), obs_size_px=32)
    for cap, out, want in ((None, "a", 20), (7, "b", 7)):
        with pytest.raises(Built):
            run_curriculum(f, None, "isar", ISARConfig(workers=0, seed=0),
                           CurriculumConfig(levels_m=(45.0,), stage_episodes=2,
                                            teacher="none", max_steps=cap),
                           out_dir=tmp_path / out, net_cfg=tiny_net())
        assert seen[-1][0] == 45.0 and seen[-1][2] == want, seen
    with pytest.raises(ConfigError, match="max_steps"):
        CurriculumConfig(max_steps=0)


def test_meta_update_clip_scales_the_summed_gradient():
    factory = multi_task_factory(3)
    meta = MetaConfig(episodes=4, workers=0, batch_tasks=2, meta_lr=1e-2, seed=0,
                      meta_max_grad_norm=1e-3)
    t = MetaTrainer(factory, tiny_net(), "a3c", base_config("a3c", {}), meta,
                    keep_task_grads=True)
    t.train()
    for u in t.update_log:
        total = [sum(g[j] for g in u["grads"]) for j in range(len(u["psi_before"]))]
        norm = float(torch.sqrt(sum((x.double() ** 2).sum() for x in total)))
        assert u["grad_norm"] == pytest.approx(norm, rel=1e-4) and norm > 1e-3
        scale = 1e-3 / (norm + 1e-6)
        step = [float((b - a).double().pow(2).sum()) for b, a in
                zip(u["psi_before"], u["psi_after"], strict=True)]
        assert sum(step) ** 0.5 == pytest.approx(1e-2 * 1e-3, rel=1e-3)  # clipped step
        for before, after, g in zip(u["psi_before"], u["psi_after"], total, strict=True):
            assert torch.allclose(after, before - 1e-2 * scale * g, atol=1e-9)
