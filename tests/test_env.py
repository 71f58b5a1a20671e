import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from geonav.env import ENV_ID, GeoNavEnv
from geonav.errors import ConfigError, TaskError
from geonav.tasks import NavTask, TaskSet, whole_scene_tasks
from geonav.testing import tiny_taskset


def test_check_env(scene, tiny_tasks):
    check_env(GeoNavEnv(scene, tiny_tasks, render_mode="rgb_array"))


def test_registered_and_makeable(scene, tiny_tasks):
    env = gymnasium.make(ENV_ID, scene=scene, tasks=tiny_tasks, render_mode="rgb_array")
    check_env(env.unwrapped)
    obs, info = env.reset(seed=0)
    assert obs["image"].shape == (84, 84, 3) and obs["image"].dtype == np.uint8
    frame = env.render()
    assert frame.shape == (168, 504, 3)


def _rollout(env, seed, n=200):
    out = []
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(n):
        obs, r, te, tr, info = env.step(int(rng.integers(4)))
        out.append((info["cell"], r, te, tr, obs["image"].sum()))
        if te or tr:
            obs, info = env.reset()
            out.append(("reset", info["cell"]))
    return out


def test_same_seed_same_trajectory(scene, tiny_tasks):
    a = _rollout(GeoNavEnv(scene, tiny_tasks), seed=3)
    b = _rollout(GeoNavEnv(scene, tiny_tasks), seed=3)
    c = _rollout(GeoNavEnv(scene, tiny_tasks), seed=4)
    assert a == b and a != c


def test_rewards_termination_truncation(scene):
    ts = tiny_taskset(scene, cells=4, max_steps=5, target=(3, 3))
    env = GeoNavEnv(scene, ts)
    obs, info = env.reset(seed=0, options={"start_cell": (1, 3)})
    assert info["shortest_path"] == 2 and info["distance_m"] == 30.0
    assert np.array_equal(obs["target"], env.observation_at(0, (3, 3)))
    obs, r, te, tr, info = env.step(1)  # right
    assert (r, te, tr, info["cell"]) == (-0.01, False, False, (2, 3))
    obs, r, te, tr, info = env.step(0)  # forward: off the lattice
    assert info["collided"] and info["cell"] == (2, 3) and r == -0.01
    obs, r, te, tr, info = env.step(1)
    assert (r, te, tr, info["success"]) == (5.0, True, False, True)
    env.reset(options={"start_cell": (0, 0)})
    for _ in range(4):
        _, _, te, tr, _ = env.step(3)  # bump into the south edge
        assert not tr
    _, r, te, tr, info = env.step(3)
    assert tr and not te and info["steps"] == 5


def test_collision_penalty_and_obstacles(scene):
    ts = whole_scene_tasks(scene, (15.0,), step_m=15.0, size_m=240.0, seed=0)
    env = GeoNavEnv(scene, ts, collision_reward=-0.1)
    tm = env.task_maps[0]
    assert tm.blocked.any()
    ix, iy = map(int, np.argwhere(tm.blocked)[0])
    for a, (dx, dy) in enumerate(((0, 1), (1, 0), (-1, 0), (0, -1))):
        start = (ix - dx, iy - dy)
        if tm.lattice.contains(start) and tm.dist_to_target[start] > 0:
            env.reset(seed=0, options={"start_cell": start})
            _, r, _, _, info = env.step(a)
            assert info["collided"] and info["cell"] == start and r == pytest.approx(-0.11)
            break
    else:
        pytest.skip("no free neighbour of the first obstacle")


def test_starts_reachable_within_cap(scene):
    ts = whole_scene_tasks(scene, (15.0,), step_m=15.0, size_m=240.0, max_steps=6, seed=0)
    env = GeoNavEnv(scene, ts)
    for seed in range(30):
        _, info = env.reset(seed=seed)
        assert 1 <= info["shortest_path"] <= 6


def test_task_selection_and_errors(scene, tiny_tasks):
    t2 = NavTask("second", "meta", (-30, -30, 30, 30), 15.0, 45.0, (0, 0), 30)
    ts = TaskSet(scene.name, scene.scene_id, tiny_tasks.tasks + [t2])
    env = GeoNavEnv(scene, ts, task_sampling="cycle")
    assert [env.reset()[1]["task"] for _ in range(3)] == ["tiny", "second", "tiny"]
    assert env.reset(options={"task": "second"})[1]["alt_m"] == 45.0
    with pytest.raises(TaskError, match="unknown task"):
        env.reset(options={"task": "nope"})
    with pytest.raises(ConfigError):
        GeoNavEnv(scene, ts, render_mode="human")
    other = TaskSet("Z", "0" * 16, tiny_tasks.tasks)
    with pytest.raises(TaskError, match="made for scene"):
        GeoNavEnv(scene, other)
