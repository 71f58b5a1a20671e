"""Packed runs: R runs in one process batch equal the same runs made alone."""

from dataclasses import replace

import pytest
import torch
from batched_helpers import float64

from geonav.errors import ConfigError
from geonav.policy.batched.isar import BatchedISARTrainer
from geonav.policy.batched.packed import pack, train_packed
from geonav.policy.batched.ppo import BatchedPPOTrainer, PPOConfig
from geonav.policy.batched.savn import BatchedSAVNTrainer
from geonav.policy.batched.trainer import BatchedA3CTrainer
from geonav.policy.checkpoint import load_checkpoint
from geonav.policy.config import A3CConfig
from geonav.policy.meta_config import ISARConfig, SAVNConfig
from geonav.policy.testing import tiny_env_factory, tiny_net

SEEDS = (3, 5)
CASES = {
    "a3c": (BatchedA3CTrainer, A3CConfig(episodes=10, t_max=5, lr=3e-3, max_grad_norm=0.05)),
    "ppo": (BatchedPPOTrainer, PPOConfig(episodes=10, t_max=4, lr=3e-3, epochs=2,
                                         minibatches=2, max_grad_norm=0.05)),
    "isar": (BatchedISARTrainer, ISARConfig(episodes=10, n_steps=2, k_segments=2, lr=3e-3,
                                            alpha=0.1, max_grad_norm=0.05)),
    "savn": (BatchedSAVNTrainer, SAVNConfig(episodes=10, k_steps=2, inner_steps=2, lr=3e-3,
                                            inner_lr=0.1, max_grad_norm=0.05)),
    "isar-noflush": (BatchedISARTrainer, ISARConfig(episodes=10, n_steps=2, k_segments=2,
                                                    lr=3e-3, alpha=0.1, max_grad_norm=0.05,
                                                    flush_partial_window=False)),
    "isar-ppo": (BatchedISARTrainer, ISARConfig(episodes=10, n_steps=2, k_segments=2, lr=3e-3,
                                                alpha=0.1, max_grad_norm=0.05,
                                                base_loss="ppo", ppo_epochs=2)),
}


def all_params(trainer):
    """The policy's parameters and those of the modules beside it (SAVN's loss)."""
    out = dict(trainer.model.named_parameters())
    for name, m in trainer.aux.items():
        out.update({f"{name}.{n}": p for n, p in m.named_parameters()})
    return out


@pytest.mark.parametrize("algo", sorted(CASES))
def test_two_packed_runs_equal_the_runs_alone(algo):
    check_packed_equals_alone(algo, "random", 4)


@pytest.mark.parametrize("algo,batch", [("a3c", 1), ("a3c", 3), ("ppo", 3), ("isar", 1),
                                        ("isar", 3), ("savn", 3)])
def test_two_packed_runs_with_the_trainable_cnn_equal_the_runs_alone(algo, batch):
    check_packed_equals_alone(algo, "cnn", batch)


def check_packed_equals_alone(algo, encoder, batch):
    """Two runs packed, 3 updates: the same loss columns, parameters (1e-10) and draws as
    each run made alone (float64)."""
    cls, cfg = CASES[algo]
    # SAVN: episodes that end before the cap, so that the runs' rounds differ in length
    px = 20 if encoder == "cnn" else 32  # the CNN's smallest input: F = 32, fast tests
    cap = (100 if encoder == "random" else 30) if algo == "savn" else 6
    factory = tiny_env_factory(cells=4, max_steps=cap, obs_size_px=px)
    net = tiny_net(encoder, px, size=16)
    if algo == "savn":  # a near-uniform first policy: random walks that find the target
        net = replace(net, actor_init_std=0.01)

    def member(seed):
        return float64(cls(factory, net, replace(cfg, seed=seed), batch=batch,
                           tensorboard=False))

    members = [member(s) for s in SEEDS]
    driver = pack(members)
    driver._setup()
    longest = []  # per update, each run's longest episode (SAVN: its own round's length)
    for _ in range(3):
        finals, stats = driver.update()
        longest.append([max((f["length"] for f in finals if f["slot"] // batch == r),
                            default=0)
                        for r in range(2)])
    if algo == "savn" and encoder == "random":  # a run's round ended before the packed
        # round: it waited, drawing none
        assert any(a != b for a, b in longest), longest
    moved = 0.0
    for i, seed in enumerate(SEEDS):
        alone = member(seed)
        alone._setup()
        for _ in range(3):
            _, alone_stats = alone.update()
        assert stats[i] == pytest.approx(alone_stats, rel=1e-9, abs=1e-12)  # loss columns
        mine, other = all_params(members[i]), all_params(members[1 - i])
        for n, p in all_params(alone).items():
            torch.testing.assert_close(mine[n], p, atol=1e-10, rtol=1e-10, msg=n)
            moved = max(moved, float((p - other[n]).detach().abs().max()))
        assert alone.rng.random() == members[i].rng.random()  # the same draws were made
    assert moved > 1e-4  # the two runs differ: the comparison is not trivial


def test_packed_run_folders(tmp_path):
    factory = tiny_env_factory(cells=4, max_steps=6)
    net = tiny_net("random", 32, size=16)
    members = [BatchedA3CTrainer(factory, net, A3CConfig(episodes=12 + 4 * s, t_max=4, seed=s,
                                                         eval_every=0),
                                 batch=4, out_dir=tmp_path / f"run_{s}", tensorboard=False)
               for s in (0, 1)]
    results = train_packed(members)
    assert [r.episodes for r in results] == [12, 16]
    for s in (0, 1):
        ck = load_checkpoint(tmp_path / f"run_{s}" / "checkpoints" / "final.pt")
        assert ck.episodes == 12 + 4 * s
        rows = (tmp_path / f"run_{s}" / "metrics.csv").read_text().splitlines()
        assert len(rows) == 13 + 4 * s
        assert (tmp_path / f"run_{s}" / "config.json").exists()


def test_packing_refuses_different_networks():
    factory = tiny_env_factory(cells=4, max_steps=6)
    members = [BatchedA3CTrainer(factory, tiny_net("random", 32, size=n), A3CConfig(),
                                 batch=4, tensorboard=False) for n in (16, 32)]
    with pytest.raises(ConfigError, match="differ in network"):
        pack(members)
