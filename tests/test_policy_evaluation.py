"""Greedy and sampled evaluation from every start cell (issue 10)."""

from __future__ import annotations

import numpy as np
import pytest

from geonav.env import GeoNavEnv
from geonav.policy.evaluation import all_starts, evaluate, evaluate_both
from geonav.testing import tiny_taskset


class Oracle:
    """Always takes a BFS shortest-path action (reads the cell from info)."""

    def __init__(self, env):
        self.env = env

    def reset(self):
        pass

    def act(self, obs, info=None):
        tm = self.env.unwrapped.task_maps[info["task_index"]]
        return tm.shortest_path_action(tuple(info["cell"]))


class North:
    def reset(self):
        pass

    def act(self, obs, info=None):
        return 0


@pytest.fixture()
def env(flat_scene):
    return GeoNavEnv(flat_scene, tiny_taskset(flat_scene, cells=5, max_steps=20,
                                              target=(2, 4)))


def test_all_starts_lists_every_valid_start_and_samples_above_the_cap(env):
    starts = all_starts(env)
    assert len(starts) == 24 and len(set(starts)) == 24          # 25 cells less the target
    sample = all_starts(env, max_starts=10, seed=3)
    assert len(sample) == 10 and set(sample) <= set(starts)
    assert sample == all_starts(env, max_starts=10, seed=3)


def test_oracle_scores_one_and_north_scores_what_the_lattice_implies(env):
    starts = all_starts(env)
    res = evaluate(Oracle(env), env, starts=starts)
    assert res.success_rate == 1.0 and res.spl == pytest.approx(1.0)
    north = evaluate(North(), env, starts=starts)
    # only the starts below the target in its column reach it by going north
    expected = sum(1 for _, c in starts if c[0] == 2 and c[1] < 4) / len(starts)
    assert north.success_rate == pytest.approx(expected)
    assert north.mean_collisions > 0


def test_evaluate_both_reports_greedy_and_sampled(env):
    out = evaluate_both(Oracle(env), env, max_starts=None)
    row = out["row"]
    assert out["starts"] == 24
    assert row["greedy_sr"] == 1.0 and row["sampled_sr"] == 1.0
    assert row["greedy_length_ratio"] == pytest.approx(1.0)
    assert np.isfinite(row["greedy_spl"])
