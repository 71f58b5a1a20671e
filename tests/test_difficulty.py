"""Exact chance figures of a task: random-walk DP vs Monte Carlo and closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from geonav.difficulty import best_blind, start_success, success_within, task_difficulty
from geonav.errors import TaskError
from geonav.tasks import ACTION_MOVES, NavTask, ObstacleModel, TaskMap, bfs_distances


def _task_map(blocked: np.ndarray, target: tuple[int, int], max_steps: int) -> TaskMap:
    nx, ny = blocked.shape
    task = NavTask("t", "meta", (0.0, 0.0, 10.0 * nx, 10.0 * ny), 10.0, 300.0, target,
                   max_steps, ObstacleModel())
    return TaskMap(task, blocked, bfs_distances(blocked, target))


def _monte_carlo(blocked, target, start, max_steps, n, rng, probs=(0.25,) * 4):
    nx, ny = blocked.shape
    hits = 0
    for _ in range(n):
        x, y = start
        for _ in range(max_steps):
            dx, dy = ACTION_MOVES[rng.choice(4, p=probs)]
            u, v = x + dx, y + dy
            if 0 <= u < nx and 0 <= v < ny and not blocked[u, v]:
                x, y = u, v
            if (x, y) == target:
                hits += 1
                break
    return hits / n


def test_one_by_two_lattice_closed_form():
    # From the other cell only one of the four moves reaches the target; the three others
    # are refused (out of the region) and leave the agent in place: P = 1 - (3/4)^T.
    blocked = np.zeros((2, 1), bool)
    for t in (0, 1, 2, 5, 20):
        p = success_within(blocked, (1, 0), t)
        assert p[0, 0] == pytest.approx(1 - 0.75 ** t, abs=1e-12)
        assert p[1, 0] == 1.0
    tm = _task_map(blocked, (1, 0), 7)
    assert start_success(tm) == pytest.approx(1 - 0.75 ** 7)
    sr, q = best_blind(tm)  # always east: certain success in one step
    assert sr == pytest.approx(1.0) and q == (0.0, 1.0, 0.0, 0.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_dp_equals_monte_carlo_with_obstacles(seed):
    rng = np.random.default_rng(seed)
    blocked = np.zeros((5, 4), bool)
    blocked[2, 1:4] = True          # a wall with a gap at the bottom
    blocked[4, 0] = True
    target, T = (4, 3), 25
    p = success_within(blocked, target, T)
    n = 4000
    for start in [(0, 0), (1, 3), (3, 2)]:
        est = _monte_carlo(blocked, target, start, T, n, rng)
        se = max(np.sqrt(est * (1 - est) / n), 1e-3)
        assert abs(p[start] - est) < 3 * se, (start, p[start], est)
    probs = (0.1, 0.5, 0.1, 0.3)
    est = _monte_carlo(blocked, target, (0, 0), T, n, rng, probs)
    pb = success_within(blocked, target, T, probs)[0, 0]
    assert abs(pb - est) < 3 * max(np.sqrt(est * (1 - est) / n), 1e-3)


def test_task_difficulty_figures_and_batch():
    blocked = np.zeros((6, 6), bool)
    blocked[3, 0:5] = True
    tm = _task_map(blocked, (5, 5), 30)
    d = task_difficulty(tm)
    starts = tm.start_cells()
    assert d.n_starts == len(starts) and d.max_steps == 30
    assert d.mean_shortest_path == pytest.approx(np.mean([tm.dist_to_target[c] for c in starts]))
    assert 0.0 < d.random_walk_sr < d.blind_sr <= 1.0
    assert d.random_walk_sr == pytest.approx(start_success(tm))
    qs = np.array([[0.25] * 4, d.blind_probs])
    batch = start_success(tm, None, qs)
    assert batch[0] == pytest.approx(d.random_walk_sr) and batch[1] == pytest.approx(d.blind_sr)
    with pytest.raises(TaskError, match="summing to 1"):
        success_within(blocked, (5, 5), 3, (0.5, 0.5, 0.5, 0.0))


def test_env_difficulty_matches_the_quick_style_task(tiny_tasks, scene):
    from geonav.difficulty import env_difficulty
    from geonav.env import GeoNavEnv

    env = GeoNavEnv(scene, tiny_tasks)
    d = env_difficulty(env)
    tm = env.unwrapped.task_maps[0]
    assert d["random_walk_sr"] == pytest.approx(start_success(tm, env.unwrapped.max_steps_of(0)))
    assert set(d["tasks"]) == {"tiny"}


# -- issue 29: the view-blind line ----------------------------------------------------------

def test_view_blind_dp_equals_monte_carlo_of_the_best_fixed_distribution():
    rng = np.random.default_rng(3)
    blocked = np.zeros((5, 5), bool)
    blocked[1, 1:3] = True
    tm = _task_map(blocked, (3, 1), 12)
    sr, q = best_blind(tm)
    starts = tm.start_cells()
    n = 600
    est = np.mean([_monte_carlo(blocked, (3, 1), s, 12, n, rng, q) for s in starts])
    se = np.sqrt(est * (1 - est) / (n * len(starts)))
    assert abs(sr - est) < 4 * max(se, 1e-3), (sr, est)
    # no other fixed distribution (MC) beats it by more than noise
    for probs in [(0.25,) * 4, (0.1, 0.6, 0.1, 0.2), (0.4, 0.4, 0.1, 0.1)]:
        other = np.mean([_monte_carlo(blocked, (3, 1), s, 12, 300, rng, probs)
                         for s in starts])
        assert other <= sr + 0.03


def test_corner_target_is_solved_blind_centre_target_is_not():
    from geonav.difficulty import blind_at_most, chance_floor

    blocked = np.zeros((15, 15), bool)
    corner = task_difficulty(_task_map(blocked, (14, 0), 40))
    centre = task_difficulty(_task_map(blocked, (7, 7), 40))
    assert corner.blind_sr > 0.97          # a fixed diagonal bias (east + south) works
    assert sorted(corner.blind_probs)[-2:] == [0.5, 0.5]
    assert centre.blind_sr < 0.3 < corner.blind_sr
    assert centre.random_walk_sr < centre.blind_sr
    tm = _task_map(blocked, (7, 7), 40)
    assert blind_at_most(tm, 0.3) and not blind_at_most(_task_map(blocked, (14, 0), 40), 0.3)
    assert blind_at_most(tm, centre.blind_sr) and not blind_at_most(tm, centre.blind_sr - 1e-6)
    assert chance_floor(0.041, 0.996) == pytest.approx(0.998)
    assert chance_floor(0.3, None) == pytest.approx(0.65)
