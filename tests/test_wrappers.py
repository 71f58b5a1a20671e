import pickle

import cv2
import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from geonav.camera import Camera
from geonav.env import ENV_ID, GeoNavEnv
from geonav.errors import ConfigError
from geonav.wrappers import DictImageObservation


@pytest.fixture()
def env(scene, tiny_tasks):
    return GeoNavEnv(scene, tiny_tasks)


@pytest.mark.filterwarnings("ignore:.*is different from the unwrapped version")
def test_resize_and_grey_every_image_key(env):
    wrapped = DictImageObservation(env, (32, 40), grey=True)
    assert wrapped.observation_space["image"].shape == (32, 40, 1)
    assert wrapped.observation_space["target"].shape == (32, 40, 1)
    check_env(wrapped.unwrapped, skip_render_check=True)
    check_env(wrapped, skip_render_check=True)
    obs, _ = wrapped.reset(seed=2)
    raw, _ = env.reset(seed=2)  # same seed: same start
    want = cv2.cvtColor(cv2.resize(raw["image"], (40, 32), interpolation=cv2.INTER_AREA),
                        cv2.COLOR_RGB2GRAY)
    assert obs["image"].shape == (32, 40, 1) and np.array_equal(obs["image"][:, :, 0], want)
    assert obs["image"] in wrapped.observation_space["image"]
    obs, *_ = wrapped.step(1)
    assert obs["target"].shape == (32, 40, 1) and obs["target"].dtype == np.uint8


def test_options_keys_and_errors(env):
    flat = DictImageObservation(env, grey=True, keep_dim=False)
    assert flat.observation_space["image"].shape == (84, 84)
    only = DictImageObservation(env, 16, keys=["image"])
    obs, _ = only.reset(seed=0)
    assert obs["image"].shape == (16, 16, 3) and obs["target"].shape == (84, 84, 3)
    assert pickle.loads(pickle.dumps(only)).observation_space == only.observation_space
    with pytest.raises(ConfigError, match="not an"):
        DictImageObservation(env, 16, keys=["nope"])
    with pytest.raises(ConfigError, match="Dict"):
        DictImageObservation(gymnasium.make("CartPole-v1"), 16)
    with pytest.raises(ConfigError, match="shape"):
        DictImageObservation(env, (0, 16))


def test_camera_route_renders_at_the_source(scene, tiny_tasks):
    native = gymnasium.make(ENV_ID, scene=scene, tasks=tiny_tasks, camera=Camera(42))
    obs, _ = native.reset(seed=0, options={"start_cell": (1, 1)})
    assert obs["image"].shape == (42, 42, 3)
    resized = DictImageObservation(GeoNavEnv(scene, tiny_tasks), 42)
    small, _ = resized.reset(seed=0, options={"start_cell": (1, 1)})
    # the same ground seen two ways: close, not identical (42 px rendered vs 84 px averaged)
    diff = np.abs(obs["image"].astype(int) - small["image"].astype(int)).mean()
    assert 0 < diff < 12


def test_sb3_checker_accepts_the_wrapped_env(env):
    pytest.importorskip("stable_baselines3", reason="needs the sb3 extra")
    from stable_baselines3.common.env_checker import check_env as sb3_check

    sb3_check(DictImageObservation(env, 48, grey=True), warn=True)
