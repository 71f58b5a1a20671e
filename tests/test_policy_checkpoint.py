"""Checkpoints: round trip, refusal of mismatched/corrupt files, resume."""

from __future__ import annotations

import json

import pytest
import torch

from geonav.errors import CheckpointError
from geonav.policy.a3c import A3CTrainer, train_a3c
from geonav.policy.checkpoint import check_compatible, load_checkpoint, save_checkpoint
from geonav.policy.config import A3CConfig
from geonav.policy.testing import tiny_env_factory, tiny_net


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    res = train_a3c(tiny_env_factory(), tiny_net(), A3CConfig(episodes=4, workers=0),
                    out_dir=out)
    return out, res


def test_round_trip_with_optimizer_state(trained):
    out, res = trained
    ck = load_checkpoint(out / "checkpoints" / "final.pt")
    assert ck.episodes == 4
    model = ck.build_model()
    for (k, a), b in zip(res.model.state_dict().items(), model.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    trainer = A3CTrainer(tiny_env_factory(), None, A3CConfig(episodes=5, workers=0),
                         resume=out / "checkpoints" / "final.pt")
    saved = ck.optimizer_state["state"]
    loaded = trainer.optimizer.state_dict()["state"]
    assert saved.keys() == loaded.keys()
    for i in saved:
        for key in ("step", "exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
            assert torch.equal(saved[i][key].float(), loaded[i][key].float()), key
    assert float(saved[0]["step"]) > 0


def test_meta_contract(trained):
    out, _ = trained
    meta = load_checkpoint(out / "checkpoints" / "final.pt").meta
    json.dumps(meta)
    assert meta["obs_size_px"] == 32 and meta["fov_deg"] == 90.0
    assert meta["action_meanings"] == ["forward", "right", "left", "backward"]
    assert meta["alt_m"] == 75.0 and meta["step_m"] == 15.0
    assert meta["algorithm"] == "a3c" and meta["encoder"]["kind"] == "random"
    assert meta["net"]["lstm_size"] == 64 and meta["scene_id"] and meta["task_fingerprint"]
    assert meta["geonav_version"]


def test_loads_with_weights_only(trained):
    out, _ = trained
    blob = torch.load(out / "checkpoints" / "final.pt", weights_only=True)
    assert blob["format"] == "geonav-policy"


def test_mismatched_env_is_refused(trained):
    out, _ = trained
    meta = load_checkpoint(out / "checkpoints" / "final.pt").meta
    with pytest.raises(CheckpointError, match="32 px"):
        check_compatible(meta, tiny_env_factory(obs_size_px=48)())
    env = tiny_env_factory()()
    with pytest.raises(CheckpointError, match="actions"):
        check_compatible({**meta, "action_meanings": ["north", "east", "west", "south"]}, env)
    with pytest.raises(CheckpointError, match="encoder"):
        check_compatible(meta, env, net_cfg=tiny_net(encoder="cnn"))
    from dataclasses import replace

    net = load_checkpoint(out / "checkpoints" / "final.pt").net_config
    ff = replace(net, recurrent=False)
    with pytest.raises(CheckpointError, match="recurrent=True, but this run asks for "
                                              "recurrent=False"):
        check_compatible(meta, env, net_cfg=ff)
    ff_meta = {**meta, "net": {**meta["net"], "recurrent": False}}
    check_compatible(ff_meta, env, net_cfg=ff)
    with pytest.raises(CheckpointError, match="separate_critic=False, but this run asks for "
                                              "separate_critic=True"):
        check_compatible(ff_meta, env, net_cfg=replace(ff, separate_critic=True))
    with pytest.raises(CheckpointError, match="px"):
        A3CTrainer(tiny_env_factory(obs_size_px=48), None, A3CConfig(episodes=8, workers=0),
                   resume=out / "checkpoints" / "final.pt")


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty", "not_a_policy"])
def test_corrupt_checkpoint_is_refused_and_nothing_is_overwritten(trained, tmp_path, damage):
    out, _ = trained
    good = (out / "checkpoints" / "final.pt").read_bytes()
    bad = tmp_path / "bad.pt"
    if damage == "truncated":
        bad.write_bytes(good[: len(good) // 2])
    elif damage == "garbage":
        bad.write_bytes(b"\x00garbage" * 100)
    elif damage == "empty":
        bad.write_bytes(b"")
    else:
        torch.save({"weights": torch.zeros(3)}, bad)
    with pytest.raises(CheckpointError, match="bad.pt"):
        load_checkpoint(bad)
    run = tmp_path / "run"
    with pytest.raises(CheckpointError):
        train_a3c(tiny_env_factory(), None, A3CConfig(episodes=8, workers=0), out_dir=run,
                  resume=bad)
    assert not run.exists()


def test_missing_checkpoint():
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint("/nonexistent/x.pt")


def test_atomic_write_keeps_the_old_file_on_error(tmp_path):
    path = tmp_path / "c.pt"
    save_checkpoint(path, {"w": torch.ones(2)}, {"net": {}})
    before = path.read_bytes()
    with pytest.raises(TypeError):
        save_checkpoint(path, {"w": torch.zeros(2)}, {"net": {}, "bad": object()})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]


def test_resume_continues_the_episode_count_exactly(tmp_path):
    factory = tiny_env_factory()
    net = tiny_net()
    straight = train_a3c(factory, net, A3CConfig(episodes=10, workers=0, seed=5))
    run = tmp_path / "run"
    first = train_a3c(factory, net, A3CConfig(episodes=6, workers=0, seed=5,
                                              checkpoint_every=3), out_dir=run)
    assert first.episodes == 6
    resumed = train_a3c(factory, None, A3CConfig(episodes=10, workers=0, seed=5),
                        out_dir=run, resume=run / "checkpoints" / "latest.pt")
    assert resumed.start_episode == 6 and resumed.episodes == 10
    assert [r["episode"] for r in resumed.records] == [7, 8, 9, 10]
    # Weights, Adam state and RNG state were all restored: same result as one straight run.
    assert [r["return"] for r in resumed.records] == [r["return"] for r in straight.records[6:]]
    for a, b in zip(straight.model.parameters(), resumed.model.parameters(), strict=True):
        assert torch.allclose(a, b, atol=1e-7)
    rows = (run / "metrics.csv").read_text().splitlines()
    assert len(rows) == 1 + 10  # one header, appended rows
    assert load_checkpoint(run / "checkpoints" / "final.pt").episodes == 10
