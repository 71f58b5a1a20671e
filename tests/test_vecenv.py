"""LatticeVecEnv against the reference GeoNavEnv: trajectories, tables, resets, errors."""

import numpy as np
import pytest

from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.errors import TaskError
from geonav.tasks import NavTask, TaskSet
from geonav.vecenv import LatticeVecEnv


@pytest.fixture(scope="module")
def two_task_env(scene):
    """Two tasks at 15 m over towers and houses (blocked cells), different lattices."""
    t1 = NavTask("a", "scene", (-60.0, -60.0, 60.0, 60.0), 15.0, 15.0, (7, 7), 12)
    t2 = NavTask("b", "scene", (-90.0, -30.0, 0.0, 60.0), 15.0, 15.0, (0, 2), 9)
    ts = TaskSet(scene.name, scene.scene_id, [t1, t2])
    return GeoNavEnv(scene, ts, camera=Camera(16, 90.0))


def _reference(env, task, start, actions):
    obs, info = env.reset(options={"task": task, "start_cell": start})
    out = [(info["cell"], 0.0, False, False, False, obs["image"].sum(), obs["target"].sum())]
    for a in actions:
        obs, r, te, tr, info = env.step(a)
        out.append((info["cell"], r, te, tr, info["collided"], obs["image"].sum(),
                    obs["target"].sum()))
        if te or tr:
            break
    return out, info


def test_forced_trajectories_equal_geonavenv(two_task_env):
    env = two_task_env
    assert any(tm.blocked.any() for tm in env.task_maps)  # collisions with obstacles happen
    rng = np.random.default_rng(0)
    b = 6
    tasks = [i % 2 for i in range(b)]
    starts = [env.start_cells(t)[int(rng.integers(len(env.start_cells(t))))] for t in tasks]
    actions = rng.integers(0, 4, size=(14, b))
    refs = [_reference(env, tasks[s], starts[s], actions[:, s].tolist()) for s in range(b)]
    venv = LatticeVecEnv(env, b)
    venv.reset(seed=1, tasks=tasks, starts=starts)
    images = venv.image_table()
    got = [[(venv.info(s)["cell"], 0.0, False, False, False,
             images[venv.view_index[s]].sum(), images[venv.target_index[s]].sum())]
           for s in range(b)]
    alive = np.ones(b, bool)
    for t in range(actions.shape[0]):
        res = venv.step(actions[t], autoreset=False)
        for s in np.nonzero(alive)[0]:
            got[s].append((venv.info(s)["cell"], float(res.rewards[s]), bool(res.terminated[s]),
                           bool(res.truncated[s]), bool(res.collided[s]),
                           images[res.final_view[s]].sum(), images[venv.target_index[s]].sum()))
        for f in [f for f in res.final if alive[f["slot"]]]:
            ref_info = refs[f["slot"]][1]
            assert f["length"] == ref_info["steps"]
            assert f["success"] == ref_info["success"]
            assert f["shortest_path"] == ref_info["shortest_path"]
            assert venv.info(f["slot"], bool(res.collided[f["slot"]])) == ref_info
        alive &= ~res.done
        if not alive.any():
            break
    for s in range(b):
        assert got[s] == refs[s][0]
    assert any(r[4] for ref in refs for r in ref[0])  # some moves were refused


def test_autoreset_and_start_distribution(two_task_env):
    venv = LatticeVecEnv(two_task_env, 64)
    venv.reset(seed=3)
    assert set(venv.task.tolist()) == {0, 1}
    seen = set()
    for _ in range(40):
        res = venv.step(venv.np_random.integers(0, 4, 64))
        for f in res.final:
            assert venv.steps[f["slot"]] == 0  # reset in the same step
        for s in range(64):
            ti, cell = int(venv.task[s]), tuple(int(c) for c in venv.start[s])
            assert cell in two_task_env.start_cells(ti)
            seen.add((ti, cell))
    n_starts = sum(len(two_task_env.start_cells(i)) for i in range(2))
    assert len(seen) > 0.8 * n_starts  # starts cover the valid set


def test_pinned_slot_tasks_and_errors(two_task_env):
    venv = LatticeVecEnv(two_task_env, 4, slot_tasks=[1, 1, 0, 1])
    venv.reset(seed=0)
    assert venv.task.tolist() == [1, 1, 0, 1]
    blocked = np.argwhere(two_task_env.task_maps[0].blocked)
    with pytest.raises(TaskError):
        venv.reset_slots([0], tasks=[0], starts=[tuple(blocked[0])])
    with pytest.raises(TaskError):
        venv.reset_slots([0], tasks=[0], starts=[(99, 0)])
    with pytest.raises(ValueError):
        venv.step([0, 1, 2, 7])


def test_tables_match_env_views(two_task_env):
    venv = LatticeVecEnv(two_task_env, 2)
    table = venv.image_table()
    assert table.shape[0] == sum(tm.lattice.n_cells for tm in two_task_env.task_maps)
    for v in (0, 17, table.shape[0] - 1):
        ti, cell = venv.view_cells()[v]
        assert venv.view_of(ti, cell) == v
        np.testing.assert_array_equal(table[v], two_task_env.observation_at(ti, cell))
