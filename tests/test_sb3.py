"""Stable-Baselines3 on GeoNavEnv: its env checker, PPO, its success-rate logging."""

import csv
import math
import warnings

import pytest

from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.tasks import NavTask, TaskSet

sb3 = pytest.importorskip("stable_baselines3", reason="needs the sb3 extra: "
                          "pip install 'geonav[sb3]' (scripts/setup_env.sh installs it)")


@pytest.fixture()
def small_env(scene):
    """A 3 x 3 lattice at 75 m seen by a 48 px camera (NatureCNN needs >= 36 px)."""
    task = NavTask("small", "meta", (-22.5, -22.5, 22.5, 22.5), 15.0, 75.0, (2, 2), 12)
    ts = TaskSet(scene.name, scene.scene_id, [task], camera=Camera(48))
    return GeoNavEnv(scene, ts)


def test_sb3_env_checker(small_env):
    from stable_baselines3.common.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(small_env, warn=True)
    assert not [w for w in caught if "geonav" in str(w.filename)]


def test_ppo_runs_a_few_hundred_steps_and_logs_success_rate(small_env, tmp_path):
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import configure

    torch.set_num_threads(1)
    model = PPO("MultiInputPolicy", small_env, n_steps=128, batch_size=64, n_epochs=1,
                seed=0, device="cpu", policy_kwargs=dict(net_arch=[16]))
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(total_timesteps=256)
    assert model.num_timesteps == 256
    with open(tmp_path / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and "rollout/success_rate" in rows[-1]
    rates = [float(r["rollout/success_rate"]) for r in rows if r["rollout/success_rate"]]
    assert rates and all(0.0 <= v <= 1.0 for v in rates)
    # SB3 fills its success buffer from info["is_success"] at every episode end
    assert len(model.ep_success_buffer) == len(model.ep_info_buffer) > 0
    assert math.isclose(rates[-1], sum(model.ep_success_buffer) / len(model.ep_success_buffer))
