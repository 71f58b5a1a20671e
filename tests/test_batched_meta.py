"""Batched meta-training (SAVN base, E = 1): the reference MetaTrainer's meta update."""

import functools
from dataclasses import replace

import torch

from geonav.env import GeoNavEnv
from geonav.policy.batched.meta import BatchedMetaSAVN
from geonav.policy.meta import MetaTrainer
from geonav.policy.meta_config import MetaConfig, SAVNConfig
from geonav.policy.testing import tiny_env_factory, tiny_net


def test_first_meta_update_equals_reference(tmp_path):
    factory = tiny_env_factory(cells=5, max_steps=12)
    net = tiny_net("random", 32, size=16)
    base = SAVNConfig(k_steps=3, inner_steps=2, inner_lr=0.5)
    meta = MetaConfig(episodes=1, workers=0, batch_tasks=1, meta_lr=0.1, seed=4)
    ref = MetaTrainer(factory, net, "savn", base, meta, tensorboard=False)
    ref.train()
    bat = BatchedMetaSAVN(factory, net, base, meta, out_dir=tmp_path, tensorboard=False)
    res = bat.train()
    assert res.episodes == 1 and bat.meta_updates == 1
    for (n, a), b in zip(ref.model.named_parameters(), bat.model.parameters(), strict=True):
        torch.testing.assert_close(b.detach(), a.detach(), atol=1e-6, rtol=1e-5, msg=n)
    for a, b in zip(ref.aux["interaction_loss"].parameters(),
                    bat.aux["interaction_loss"].parameters(), strict=True):
        torch.testing.assert_close(b.detach(), a.detach(), atol=1e-6, rtol=1e-5)
    cfg = (tmp_path / "config.json").read_text()
    assert '"meta-savn"' in cfg and '"meta_lr": 0.1' in cfg


def test_slots_run_the_batch_tasks_in_cyclic_order():
    u = tiny_env_factory(cells=4, max_steps=6)().unwrapped
    tasks = [u.tasks[0], replace(u.tasks[0], name="tiny-b", target_cell=(0, 0))]
    two = functools.partial(GeoNavEnv, u.scene, tasks, camera=u.camera)
    bat = BatchedMetaSAVN(two, tiny_net("random", 32, size=16), SAVNConfig(k_steps=3),
                          MetaConfig(episodes=9, batch_tasks=3, workers=0),
                          tensorboard=False)
    res = bat.train()
    assert [r["task_index"] for r in res.records[:3]] == [0, 1, 0]
    assert sorted(r["task_index"] for r in res.records[3:6]) == [0, 1, 1]
    assert bat.meta_updates == 3
