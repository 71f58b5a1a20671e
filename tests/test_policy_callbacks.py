"""Learning curves for any run length; TensorBoard under SB3's tag names."""

import cv2
import numpy as np
import pytest

from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.policy.callbacks import (
    CSVMetrics,
    _trailing_mean,
    curve_window,
    plot_learning_curve,
    read_metrics,
    running_env_steps,
    tensorboard_callback,
)
from geonav.tasks import NavTask, TaskSet


def _records(n, *, running_total=True):
    rng = np.random.default_rng(0)
    total, out = 0, []
    for i in range(n):
        length = int(rng.integers(5, 40))
        total += length
        out.append(dict(episode=i + 1, worker=0, task="t", task_index=0,
                        **{"return": 5.0 - 0.01 * length}, length=length,
                        success=bool(i % 3), spl=0.5, collisions=0, shortest_path=4,
                        policy_loss=0.1, value_loss=0.2, entropy=1.3,
                        env_steps=total if running_total else length))
    return out


def test_window_follows_the_run_size():
    assert curve_window(50) == 5 and curve_window(12) == 1 and curve_window(30_000) == 500
    assert curve_window(12, 100) == 12 and curve_window(1000, 100) == 100
    assert curve_window(0) == 1
    # every episode gets a point, the head averaging what there is so far
    np.testing.assert_allclose(_trailing_mean(np.array([1.0, 0.0, 1.0, 1.0]), 2),
                               [1.0, 0.5, 0.5, 1.0])


def test_env_steps_axis_running_total_or_summed(tmp_path):
    rows = _records(6)
    np.testing.assert_array_equal(running_env_steps(rows), np.cumsum([r["length"] for r in rows]))
    resumed = [dict(r, env_steps=r["env_steps"] + 1000) for r in rows]  # after a resume
    assert running_env_steps(resumed)[-1] == rows[-1]["env_steps"] + 1000
    per_episode = _records(6, running_total=False)  # a column that repeats the length
    np.testing.assert_array_equal(running_env_steps(per_episode),
                                  np.cumsum([r["length"] for r in per_episode]))


@pytest.mark.parametrize("n", [3, 40])
def test_learning_curve_png_for_short_runs(tmp_path, n):
    m = CSVMetrics(tmp_path / "metrics.csv")
    for r in _records(n):
        m.on_episode(r)
    m.close()
    assert len(read_metrics(tmp_path / "metrics.csv")) == n
    out = plot_learning_curve(tmp_path / "metrics.csv", tmp_path / "curve.png")
    img = cv2.imread(str(out))
    assert img is not None and img.shape == (540, 700, 3)
    assert not list(tmp_path.glob(".*.tmp.png"))


def _scalars(log_dir):
    ea_mod = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")
    ea = ea_mod.EventAccumulator(str(log_dir))
    ea.Reload()
    return {tag: [(e.step, e.value) for e in ea.Scalars(tag)] for tag in ea.Tags()["scalars"]}


def test_tensorboard_sb3_tags_against_env_steps(tmp_path):
    pytest.importorskip("tensorboard", reason="needs the tensorboard extra: "
                        "pip install 'geonav[tensorboard]'")
    tb = tensorboard_callback(tmp_path / "tb", required=True)
    records = _records(5)
    for r in records:
        tb.on_episode(r)
    tb.on_eval(dict(episode=5, env_steps=records[-1]["env_steps"], starts=8, greedy_sr=0.75,
                    greedy_spl=0.6, sampled_sr=0.5, sampled_spl=float("nan"),
                    ablated_sr=0.25))
    tb.on_train_end(None)
    assert tb.run_dir == tmp_path / "tb" / "GEONAV_1"  # no trainer named it
    s = _scalars(tb.run_dir)
    steps = [r["env_steps"] for r in records]
    assert [x for x, _ in s["rollout/ep_len_mean"]] == steps  # x = cumulative env steps
    assert s["rollout/success_rate"][-1][1] == pytest.approx(np.mean([r["success"]
                                                                      for r in records]))
    assert s["rollout/ep_rew_mean"][0][1] == pytest.approx(records[0]["return"])
    assert s["train/entropy_loss"][0][1] == pytest.approx(-1.3)  # SB3: minus the entropy
    assert s["eval/success_rate"] == [(steps[-1], 0.75)]
    assert s["eval/sampled_success_rate"] == [(steps[-1], 0.5)]
    assert s["eval/ablated_success_rate"] == [(steps[-1], 0.25)]
    assert "eval/ablated_spl" not in s  # not in the row: nothing written
    assert "eval/sampled_spl" not in s  # NaN is not plotted
    assert {"train/policy_loss", "train/value_loss", "eval/spl", "time/episodes"} <= set(s)
    assert not [t for t in s if t.startswith("episode/")]


def test_tensorboard_tags_are_the_ones_sb3_writes(scene, tmp_path):
    """The tags shared with SB3's A2C (the closest SB3 algorithm to A3C) are spelled alike."""
    pytest.importorskip("tensorboard", reason="needs the tensorboard extra")
    pytest.importorskip("stable_baselines3", reason="needs the sb3 extra")
    import torch
    from stable_baselines3 import A2C

    torch.set_num_threads(1)
    task = NavTask("small", "meta", (-22.5, -22.5, 22.5, 22.5), 15.0, 75.0, (2, 2), 12)
    env = GeoNavEnv(scene, TaskSet(scene.name, scene.scene_id, [task], camera=Camera(48)))
    model = A2C("MultiInputPolicy", env, seed=0, device="cpu", n_steps=8,
                policy_kwargs=dict(net_arch=[16]), tensorboard_log=str(tmp_path / "sb3"))
    model.learn(total_timesteps=160, log_interval=5)
    sb3_tags = set()
    for run in (tmp_path / "sb3").iterdir():
        sb3_tags |= set(_scalars(run))
    tb = tensorboard_callback(tmp_path / "geonav", required=True)
    for r in _records(3):
        tb.on_episode(r)
    tb.on_train_end(None)
    ours = set(_scalars(tb.run_dir))
    shared = {"rollout/ep_rew_mean", "rollout/ep_len_mean", "rollout/success_rate",
              "train/policy_loss", "train/value_loss", "train/entropy_loss"}
    assert shared <= sb3_tags and shared <= ours



def test_tensorboard_eval_axis_spans_runs(tmp_path):
    """One callback over several trainers (curriculum stages): a later stage's evaluation
    (its own env_steps restart at 0) is drawn at the callback's running total."""
    pytest.importorskip("tensorboard", reason="needs the tensorboard extra")
    tb = tensorboard_callback(tmp_path / "tb", required=True)
    stage0, stage1 = _records(3), _records(2)
    for r in stage0 + stage1:
        tb.on_episode(r)
    tb.on_eval(dict(episode=2, env_steps=stage1[-1]["env_steps"], greedy_sr=0.5))
    tb.on_train_end(None)
    s = _scalars(tb.run_dir)
    assert s["eval/success_rate"] == [(s["rollout/ep_len_mean"][-1][0], 0.5)]
    assert s["eval/success_rate"][0][0] > stage1[-1]["env_steps"]


def test_tensorboard_runs_get_sb3s_sub_folders(tmp_path):
    """Two runs given one --tensorboard folder are two runs (SB3's DIR/<name>_<N>), not
    one whose step axis jumps back; a resumed run goes on in its latest folder; the event
    file is made when training starts (a run refused before leaves none)."""
    pytest.importorskip("tensorboard", reason="needs the tensorboard extra")
    from geonav.policy.callbacks import run_folder

    log_dir = tmp_path / "tb"
    refused = tensorboard_callback(log_dir, required=True)  # a run refused before training
    refused.on_train_end(None)
    assert not log_dir.exists() or not list(log_dir.rglob("events.out.tfevents*"))
    dirs = []
    for start in (0, 0, 7):  # two new runs, then a resume of the second
        tb = tensorboard_callback(log_dir, required=True)
        tb.on_train_start({"episodes": 10, "start_episode": start, "algorithm": "a3c"})
        tb.on_episode(_records(1)[0])
        tb.on_train_end(None)
        dirs.append(tb.run_dir.name)
    assert dirs == ["A3C_1", "A3C_2", "A3C_2"]
    assert run_folder(log_dir, "PPO") == log_dir / "PPO_1"  # SB3 counts per name
    assert run_folder(log_dir, "A3C", resume=True) == log_dir / "A3C_2"
    assert len(list((log_dir / "A3C_2").glob("events.out.tfevents*"))) == 2


@pytest.mark.parametrize(("algo", "policy_tag"), [("ppo", "train/policy_gradient_loss"),
                                                  ("a3c", "train/policy_loss")])
def test_losses_are_logged_per_update_under_sb3s_names(tmp_path, algo, policy_tag):
    """SB3 logs its losses once per update, its PPO's policy term as
    train/policy_gradient_loss and its A2C's as train/policy_loss; per episode only where
    the engine reports no updates (the async one)."""
    pytest.importorskip("tensorboard", reason="needs the tensorboard extra")
    records = _records(6)
    for engine in ("batched", "async"):
        tb = tensorboard_callback(tmp_path / engine, required=True)
        tb.on_train_start({"episodes": 10, "start_episode": 0, "algorithm": algo,
                           "reports_updates": engine == "batched"})
        for k, r in enumerate(records):
            tb.on_episode(r)
            if k % 2 == 1 and engine == "batched":  # an update every two episodes
                tb.on_update({"policy_loss": 0.5, "value_loss": 0.25, "entropy": 1.0,
                              "n_updates": k // 2 + 1, "env_steps": r["env_steps"]})
        tb.on_train_end(None)
        s = _scalars(tb.run_dir)
        assert tb.run_dir.name == f"{algo.upper()}_1"
        other = {"train/policy_loss", "train/policy_gradient_loss"} - {policy_tag}
        assert not other & set(s)
        steps = [x for x, _ in s[policy_tag]]
        if engine == "async":  # no updates reported: each episode's record's losses
            assert steps == [r["env_steps"] for r in records]
            continue
        assert steps == [r["env_steps"] for r in records[1::2]]  # per update only
        assert s["train/n_updates"][-1] == (records[-1]["env_steps"], 3.0)
        assert s["train/entropy_loss"][-1][1] == pytest.approx(-1.0)


def test_batched_trainer_reports_every_update(scene, tmp_path):
    """The batched engine calls on_update once per optimiser update, with the run's env
    steps so far."""
    from geonav.policy.batched.ppo import BatchedPPOTrainer, PPOConfig
    from geonav.policy.callbacks import Callback
    from geonav.policy.config import NetConfig
    from geonav.policy.envs import EnvFactory

    class _Seen(Callback):
        def __init__(self):
            self.updates, self.records = [], []

        def on_update(self, stats):
            self.updates.append(stats)

        def on_episode(self, record):
            self.records.append(record)

    path = tmp_path / "scene"
    scene.save(path)
    task = NavTask("small", "meta", (-22.5, -22.5, 22.5, 22.5), 15.0, 75.0, (2, 2), 12)
    TaskSet(scene.name, scene.scene_id, [task], camera=Camera(32)).save(tmp_path / "t.json")
    seen = _Seen()
    cfg = PPOConfig(episodes=12, workers=0, t_max=8, eval_every=0, checkpoint_every=0)
    BatchedPPOTrainer(EnvFactory(str(path), str(tmp_path / "t.json")),
                      NetConfig(encoder="random", obs_size_px=32), cfg, batch=4,
                      callbacks=[seen], tensorboard=False).train()
    assert [u["n_updates"] for u in seen.updates] == list(range(1, len(seen.updates) + 1))
    assert {"policy_loss", "value_loss", "entropy"} <= set(seen.updates[0])
    steps = [u["env_steps"] for u in seen.updates]
    assert steps == sorted(steps) and steps[-1] == sum(r["length"] for r in seen.records)
