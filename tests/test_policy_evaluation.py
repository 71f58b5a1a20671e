"""Greedy and sampled evaluation from every start cell (issue 10)."""

from __future__ import annotations

import numpy as np
import pytest

from geonav.env import GeoNavEnv
from geonav.policy.evaluation import all_starts, evaluate, evaluate_both, run_episode
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


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_lockstep_greedy_equals_the_reference_evaluation(encoder):
    import functools

    import torch

    from geonav.camera import Camera
    from geonav.policy.a3c import train_a3c
    from geonav.policy.config import A3CConfig
    from geonav.policy.encoders import build_frozen_encoder
    from geonav.policy.evaluation import evaluate_lockstep
    from geonav.policy.testing import _scene, tiny_net

    scene = _scene(0)
    ts = tiny_taskset(scene, alt_m=75.0, cells=5, max_steps=12, target=(2, 2))
    factory = functools.partial(GeoNavEnv, scene, ts, camera=Camera(32, 90.0))
    env = factory()
    torch.manual_seed(0)
    res = train_a3c(factory, tiny_net(encoder), A3CConfig(episodes=40, workers=0, lr=1e-3,
                                                          seed=0, eval_every=0))
    frozen = build_frozen_encoder(res.model.cfg)
    starts = all_starts(env)
    ref = evaluate(res.model, env, frozen=frozen, starts=starts, greedy=True)
    fast = evaluate_lockstep(res.model, env, starts, frozen=frozen, greedy=True)
    key = ("start", "success", "length", "collisions", "actions")
    assert [{k: r[k] for k in key} for r in fast.episodes] == \
        [{k: r[k] for k in key} for r in ref.episodes]
    assert fast.success_rate == ref.success_rate and fast.spl == pytest.approx(ref.spl)
    sampled = evaluate_lockstep(res.model, env, starts, frozen=frozen, greedy=False, seed=1)
    again = evaluate_lockstep(res.model, env, starts, frozen=frozen, greedy=False, seed=1)
    assert len(sampled.episodes) == len(starts)
    assert [r["actions"] for r in sampled.episodes] == [r["actions"] for r in again.episodes]


# -- view ablation (ALGORITHMS.md (f)) --------------------------------------------------------

class CornerBias:
    """Ignores the view: north or east, 50/50 (a fixed bias toward the top-right corner)."""

    def __init__(self, seed=0):
        self.rng = np.random.default_rng(seed)

    def reset(self):
        pass

    def act(self, obs, info=None):
        return int(self.rng.integers(2))  # ACTION_MOVES[0] = north, [1] = east


class Localiser:
    """Navigates by the view alone: looks its cell up from the image's bytes (every cell's
    view, rendered once), then takes the BFS shortest-path action from there."""

    def __init__(self, env):
        u = env.unwrapped
        self.task_maps = u.task_maps
        self.where = {}
        for ti, tm in enumerate(u.task_maps):
            nx, ny = tm.lattice.shape
            for x in range(nx):
                for y in range(ny):
                    self.where[u.observation_at(ti, (x, y)).tobytes()] = (ti, (x, y))

    def reset(self):
        pass

    def act(self, obs, info=None):
        ti, cell = self.where[obs["image"].tobytes()]
        tm = self.task_maps[ti]
        if cell == tm.task.target_cell or tm.dist_to_target[cell] < 0:
            return 0  # shown the target's (or a cut-off cell's) view: any move
        return tm.shortest_path_action(cell)


@pytest.fixture()
def corner_env(flat_scene):
    """5 x 5, target in the top-right corner: a north/east bias solves it blind."""
    return GeoNavEnv(flat_scene, tiny_taskset(flat_scene, cells=5, max_steps=20,
                                              target=(4, 4)))


@pytest.fixture()
def centre_env(flat_scene):
    """5 x 5, target in the centre: no fixed bias solves it."""
    return GeoNavEnv(flat_scene, tiny_taskset(flat_scene, cells=5, max_steps=20,
                                              target=(2, 2)))


def test_a_view_blind_bias_keeps_its_sr_under_view_ablation(corner_env):
    starts = all_starts(corner_env)
    plain = evaluate(CornerBias(0), corner_env, starts=starts)
    ablated = evaluate(CornerBias(0), corner_env, starts=starts, ablate_view=True)
    assert plain.success_rate >= 0.9
    assert ablated.success_rate == plain.success_rate
    assert [r["actions"] for r in ablated.episodes] == [r["actions"] for r in plain.episodes]


def test_a_policy_that_localises_by_the_view_loses_it_under_ablation(centre_env):
    from geonav.difficulty import env_difficulty

    loc = Localiser(centre_env)
    assert len(loc.where) == 25  # every cell's view is distinct
    starts = all_starts(centre_env)
    plain = evaluate(loc, centre_env, starts=starts)
    ablated = evaluate(loc, centre_env, starts=starts, ablate_view=True, seed=0)
    assert plain.success_rate == 1.0
    assert ablated.success_rate <= 0.5
    # toward the view-blind line, not above it
    assert ablated.success_rate <= env_difficulty(centre_env)["blind_sr"] + 0.1
    again = evaluate(loc, centre_env, starts=starts, ablate_view=True, seed=0)
    assert [r["actions"] for r in again.episodes] == [r["actions"] for r in ablated.episodes]
    out = evaluate_both(loc, centre_env, max_starts=None)
    assert out["row"]["greedy_sr"] == 1.0 and out["row"]["ablated_sr"] <= 0.5
    assert out["ablated"].success_rate == pytest.approx(out["row"]["ablated_sr"], abs=1e-6)


class Recorder:
    """Always north; records what it is shown."""

    def __init__(self):
        self.seen = []

    def reset(self):
        pass

    def act(self, obs, info=None):
        self.seen.append((tuple(info["cell"]), tuple(info["view_cell"]), obs["image"].copy(),
                          obs["target"].copy()))
        return 0


def test_ablated_episode_shows_another_cell_of_the_same_task_and_keeps_the_target(env):
    u = env.unwrapped
    rec = Recorder()
    start = (1, 0)
    record = run_episode(rec, env, 0, start, ablate_view=True, rng=np.random.default_rng(5))
    target = u.observation_at(0, u.task_maps[0].task.target_cell)
    assert len(rec.seen) == record["length"] == 20  # dynamics unchanged: north to the edge
    for k, (cell, shown, image, tgt) in enumerate(rec.seen):
        assert cell == (start[0], min(start[1] + k, 4))  # the info is the episode's
        assert shown != cell and u.task_maps[0].lattice.contains(shown)
        assert np.array_equal(image, u.observation_at(0, shown))
        assert np.array_equal(tgt, target)
    assert len({s for _, s, _, _ in rec.seen}) > 5  # drawn afresh at every step


def test_an_oracle_reading_the_cell_from_info_keeps_its_sr(env):
    out = evaluate_both(Oracle(env), env, max_starts=None)
    assert out["row"]["greedy_sr"] == 1.0 and out["row"]["ablated_sr"] == 1.0


def _two_task_env(scene, camera):
    from geonav.tasks import NavTask, ObstacleModel, TaskSet

    tasks = [NavTask("four", "meta", (-30.0, -30.0, 30.0, 30.0), 15.0, 75.0, (3, 3), 10,
                     ObstacleModel()),
             NavTask("five", "meta", (-37.5, -37.5, 37.5, 37.5), 15.0, 75.0, (2, 2), 12,
                     ObstacleModel())]
    return GeoNavEnv(scene, TaskSet(scene.name, scene.scene_id, tasks), camera=camera)


@pytest.mark.parametrize("encoder", ["random", "cnn", "corr"])
def test_lockstep_ablation_draws_other_cells_of_the_same_task(encoder, monkeypatch):
    import torch

    from geonav.camera import Camera
    from geonav.policy import evaluation
    from geonav.policy.config import NetConfig
    from geonav.policy.encoders import build_frozen_encoder
    from geonav.policy.model import ActorCritic
    from geonav.policy.testing import _scene, tiny_net

    env = _two_task_env(_scene(0), Camera(32, 90.0))
    cfg = NetConfig(encoder="corr", obs_size_px=32, corr_radius=6, hidden_size=32,
                    lstm_size=32) if encoder == "corr" else tiny_net(encoder, 32, size=32)
    torch.manual_seed(0)
    model, frozen = ActorCritic(cfg), build_frozen_encoder(cfg)
    starts = all_starts(env)
    calls = []
    real = evaluation.decoy_rows

    def spy(venv, u):
        rows = real(venv, u)
        calls.append((venv.task.copy(), venv.view_index.copy(), rows.copy(),
                      venv.view_task[rows]))
        return rows

    monkeypatch.setattr(evaluation, "decoy_rows", spy)
    ablated = evaluation.evaluate_lockstep(model, env, starts, frozen=frozen, seed=3,
                                           ablate_view=True)
    assert calls and len(calls) == max(r["length"] for r in ablated.episodes)
    for task, current, rows, row_task in calls:
        assert (row_task == task).all() and (rows != current).all()
    shown = np.concatenate([rows for _, _, rows, _ in calls])
    assert len(set(shown.tolist())) > 20  # spread over both lattices, not a fixed cell
    monkeypatch.setattr(evaluation, "decoy_rows", real)
    again = evaluation.evaluate_lockstep(model, env, starts, frozen=frozen, seed=3,
                                         ablate_view=True)
    assert [r["actions"] for r in again.episodes] == [r["actions"] for r in ablated.episodes]
    # the per-episode path draws the same decoys: greedy results are equal
    ref = evaluate(model, env, frozen=frozen, starts=starts, seed=3, ablate_view=True)
    key = ("start", "success", "length", "collisions", "actions")
    assert [{k: r[k] for k in key} for r in ablated.episodes] == \
        [{k: r[k] for k in key} for r in ref.episodes]
    # ablation off: exactly the evaluation without the flag
    plain = evaluation.evaluate_lockstep(model, env, starts, frozen=frozen, seed=3)
    off = evaluation.evaluate_lockstep(model, env, starts, frozen=frozen, seed=3,
                                       ablate_view=False)
    assert [r["actions"] for r in off.episodes] == [r["actions"] for r in plain.episodes]
    sampled = evaluation.evaluate_lockstep(model, env, starts, frozen=frozen, seed=3,
                                           greedy=False, ablate_view=True)
    assert len(sampled.episodes) == len(starts)


def test_evaluate_both_adds_the_ablated_columns_and_can_skip_them(env):
    from geonav.policy.evaluation import EVAL_FIELDS

    assert EVAL_FIELDS[-2:] == ("ablated_sr", "ablated_spl")
    with_ = evaluate_both(North(), env, max_starts=None)
    without = evaluate_both(North(), env, max_starts=None, ablate=False)
    assert "ablated" not in without and "ablated_sr" not in without["row"]
    assert {k: v for k, v in with_["row"].items() if not k.startswith("ablated_")} == \
        without["row"]
    # always north ignores the view: ablation changes nothing
    assert with_["row"]["ablated_sr"] == with_["row"]["greedy_sr"]
    assert with_["row"]["ablated_spl"] == with_["row"]["greedy_spl"]
