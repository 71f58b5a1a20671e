"""Packed runs: R runs in one process batch equal the same runs made alone."""

from dataclasses import replace

import torch

from geonav.policy.batched.packed import PackedA3C
from geonav.policy.batched.trainer import BatchedA3CTrainer
from geonav.policy.checkpoint import load_checkpoint
from geonav.policy.config import A3CConfig
from geonav.policy.testing import tiny_env_factory, tiny_net


def test_two_packed_runs_equal_the_runs_alone():
    factory = tiny_env_factory(cells=4, max_steps=6)
    net = tiny_net("random", 32, size=16)
    cfg = A3CConfig(episodes=10, t_max=5, lr=3e-3, max_grad_norm=0.05)  # the clip acts
    packed = PackedA3C(factory, net, cfg, seeds=[3, 5], batch=4)
    for _ in range(4):
        packed.update()
    for i, seed in enumerate([3, 5]):
        alone = BatchedA3CTrainer(factory, net, replace(cfg, seed=seed), batch=4,
                                  tensorboard=False)
        alone._setup()
        for _ in range(4):
            alone.update()
        mine = packed.model(i).state_dict()
        moved = 0.0
        for n, p in alone.model.state_dict().items():
            torch.testing.assert_close(mine[n], p, atol=1e-6, rtol=1e-5, msg=n)
        for n, p in alone.model.named_parameters():
            moved = max(moved, float((p - packed.params[n][1 - i]).detach().abs().max()))
        assert moved > 1e-4  # the two runs differ: the comparison is not trivial


def test_packed_run_folders(tmp_path):
    factory = tiny_env_factory(cells=4, max_steps=6)
    net = tiny_net("random", 32, size=16)
    recs = PackedA3C(factory, net, A3CConfig(episodes=12, t_max=4), seeds=[0, 1], batch=4,
                     out_dir=tmp_path).train()
    assert [len(r) for r in recs] == [12, 12]
    for i in range(2):
        ck = load_checkpoint(tmp_path / f"run_{i}" / "checkpoints" / "final.pt")
        assert ck.episodes == 12
        assert len((tmp_path / f"run_{i}" / "metrics.csv").read_text().splitlines()) == 13
