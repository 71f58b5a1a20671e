"""Every part of configs/paper.toml, shrunk to seconds, end to end (issue 12: "a tiny version
of each part runs end to end in the suite").

The real paper.toml is read and shrunk by :func:`shrink`: small synthetic scenes, lattices
of a few cells, two meta-tasks, budgets of a few dozen episodes below 2 W (so no run can
converge and the noise check accepts the rule, as in configs/tiny.toml), one seed, no
worker processes and the small networks of the policy tests. Everything that makes a stage
the one the paper's protocol runs stays as paper.toml has it: mode, algo, init chain,
encoder, preset, base_loss, teacher, augment, alpha, lr, lr_warmup, stop_at_convergence
and the [[compare]] tables.
"""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path
from typing import Any

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from geonav.experiments.config import ExperimentConfig, parse_config
from geonav.experiments.runner import read_result

PAPER = Path(__file__).resolve().parent.parent / "configs" / "paper.toml"

SWEEP_PARTS = ("isar-alpha", "savn-inner")
"""Parts that are sweeps over one stage (`geonav experiment sweep`) whose stage another part
already runs; test_sweep_parts_are_covered checks that, the end-to-end test does not run
them alone."""

TINY_NET = {"embed_dim": 16, "hidden_size": 32, "lstm_size": 32}
"""Network sizes of the policy tests (tests/test_policy_model.py), added to every stage."""

SHRUNK_OPTIONS = ("eval_every", "batch_tasks", "corr_radius")
"""Stage options whose values the shrink changes (the rest are kept as paper.toml has them)."""

ADDED_OPTIONS = TINY_NET
"""Stage options the shrink adds: the network sizes (a curriculum's episode cap is the tiny
task's own: CurriculumConfig.max_steps defaults to the task set's)."""

TINY_RANDOM_WALK = 0.5
"""The tasks' random-walk cap after the shrink (paper.toml: 0.05, which needs ~20 x 20 cells)."""

TINY_BLIND = 1.0
"""The tasks' view-blind cap after the shrink (paper.toml: 0.3; a fixed bias solves a 3 x 3
lattice almost always, so only the starts-on-every-side half of the rule is kept)."""

TINY_CORR_RADIUS = 6
"""encoder='corr' stages: the shift range after the shrink (32 px views allow at most 15)."""

EPISODES = 24
"""Budget of every stage (per curriculum level); below 2 W with W = 40."""


def shrink(data: dict[str, Any]) -> dict[str, Any]:
    """A copy of a paper.toml document that runs each part in seconds (see the module
    docstring); stage modes, algorithms, init chains and method options are untouched."""
    d = copy.deepcopy(data)
    d["seeds"] = [0]
    d["eval_starts"] = 8
    # budgets (EPISODES) below 2 W: no run can converge, so no noise can either
    d["convergence"] = {"window": 40, "threshold": 0.97, "hold": 0.9, "eval_threshold": 0.97}
    for scene in d["scenes"].values():
        scene.update(size_m=400.0, gsd_m=2.0)
    for task in d["tasks"].values():
        # 3 x 3 cells of 15 m; a 45 m region fits a 400 m scene with the 300 m view margin
        task.update(size_m=45.0, step_m=15.0, max_steps=8, obs_size_px=32)
        if task.get("max_random_walk") is not None:
            # chance solves a 3 x 3 lattice about a third of the time: the sampler keeps
            # its cap, loosened to what so few cells allow
            task["max_random_walk"] = TINY_RANDOM_WALK
        if task.get("max_blind") is not None:
            task["max_blind"] = TINY_BLIND
            if task.get("kind") == "scene":
                # one centred region, no other to try: 5 x 5 cells give its target start
                # cells on every side beyond the random walk's reach
                task["size_m"] = 75.0
        if task.get("kind", "meta") == "meta":
            task["count"] = min(int(task.get("count", 1)), 2)
    for stage in d["stages"].values():
        stage["episodes"] = EPISODES
        stage["workers"] = 0
        if "eval_every" in stage:
            stage["eval_every"] = EPISODES // 2
        if "batch_tasks" in stage:
            stage["batch_tasks"] = 2
        if "corr_radius" in stage:  # the largest shift a 32 px view allows is 15
            stage["corr_radius"] = min(int(stage["corr_radius"]), TINY_CORR_RADIUS)
        stage.update(TINY_NET)
    return d


def _paper_data() -> dict[str, Any]:
    return tomllib.loads(PAPER.read_text())


@pytest.fixture(scope="module")
def paper() -> ExperimentConfig:
    return parse_config(_paper_data(), str(PAPER))


@pytest.fixture(scope="module")
def tiny() -> ExperimentConfig:
    return parse_config(shrink(_paper_data()), "paper.toml (shrunk)")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One folder for the scenes and task sets of every part (made once, by hash)."""
    return tmp_path_factory.mktemp("paper-inputs")


def test_shrink_keeps_every_stage_and_comparison(paper: ExperimentConfig,
                                                 tiny: ExperimentConfig) -> None:
    assert tiny.parts() == paper.parts()
    assert tiny.compare == paper.compare
    assert set(tiny.stages) == set(paper.stages) and set(tiny.tasks) == set(paper.tasks)
    for key, st in paper.stages.items():
        small = tiny.stages[key]
        assert (small.mode, small.algo, small.tasks, small.init) == \
            (st.mode, st.algo, st.tasks, st.init), key
        assert set(st.options) <= set(small.options), key
        assert set(small.options) - set(st.options) <= set(ADDED_OPTIONS), key
        kept = {k: v for k, v in st.options.items() if k not in SHRUNK_OPTIONS}
        assert {k: small.options[k] for k in kept} == kept, key
        assert small.episodes < 2 * tiny.convergence.window and small.workers == 0
    for key, t in paper.tasks.items():
        small = tiny.tasks[key]
        assert (small.scene, small.kind, small.alt_m, small.alts_m, small.fov_deg,
                small.seed, small.max_overlap, small.max_random_walk is None,
                small.max_blind is None) == \
            (t.scene, t.kind, t.alt_m, t.alts_m, t.fov_deg, t.seed, t.max_overlap,
             t.max_random_walk is None, t.max_blind is None), key
    for key, s in paper.scenes.items():
        assert (tiny.scenes[key].synthetic, tiny.scenes[key].seed) == (s.synthetic, s.seed)


def test_sweep_parts_are_covered(paper: ExperimentConfig) -> None:
    """isar-alpha and savn-inner are one-stage parts run as sweeps; the stage each sweeps
    is a method of another part, which the end-to-end test runs."""
    for part in SWEEP_PARTS:
        stages = paper.stages_for([part])
        others = {s for p in paper.parts() if p not in SWEEP_PARTS
                  for s in paper.stages_for([p])}
        assert stages and set(stages) <= others, part


@pytest.fixture
def loaded_inits(monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Unit folder -> the checkpoint whose weights its train or meta-train unit started
    from, each load checked to have copied those weights into the unit's model (the units
    run one at a time in a thread of this process: LocalBackend(jobs=0))."""
    import torch

    from geonav.experiments import stages
    from geonav.policy.checkpoint import load_checkpoint

    seen: dict[str, str] = {}
    current: dict[str, str] = {}
    execute, load_init = stages.execute_stage, stages._load_init

    def execute_spy(p: dict[str, Any]) -> dict[str, Any]:
        current["unit"] = p["out_dir"]
        return execute(p)

    def load_spy(model: Any, path: str | None, env: Any) -> None:
        load_init(model, path, env)
        if path:
            want = load_checkpoint(path).model_state
            for name, value in model.state_dict().items():
                torch.testing.assert_close(value, want[name], msg=name)
            seen[current["unit"]] = path

    monkeypatch.setattr(stages, "execute_stage", execute_spy)
    monkeypatch.setattr(stages, "_load_init", load_spy)
    return seen


@pytest.mark.slow
# the tiny scenes are small and coarse on purpose: their warnings say so
@pytest.mark.filterwarnings(
    "ignore:scene [A-Z]. (imagery at|the scene is) :geonav.errors.GeonavWarning")
@pytest.mark.parametrize("part", [p for p in parse_config(_paper_data(), str(PAPER)).parts()
                                  if p not in SWEEP_PARTS])
def test_paper_part_runs_tiny(part: str, tiny: ExperimentConfig, inputs: Path,
                              tmp_path: Path, loaded_inits: dict[str, str]) -> None:
    from geonav.experiments.runner import run_experiments

    summary = run_experiments([tiny], tmp_path, only=[part], jobs=0,
                              shared_inputs=inputs)[0]
    root = tmp_path / tiny.name
    assert not summary["failed"], summary["failed"]
    assert (root / "report.md").exists()
    written = json.loads((root / "summary.json").read_text())
    # only this part's comparison, not another part's whose stages it also ran (wild-aug
    # runs all of wild's; isar-vs-savn all of isar-alpha's and savn-inner's)
    specs = [c for c in tiny.compare if (c.part or c.name) == part]
    assert [c["part"] for c in written["comparisons"]] == [part] * len(specs)
    for comp, spec in zip(written["comparisons"], specs, strict=True):
        assert list(comp["methods"]) == list(spec.methods)
        assert f"## {spec.name}" in (root / "report.md").read_text()
        _check_methods(tiny, comp, spec)
    _check_units(tiny, root, part, loaded_inits)


def _check_methods(tiny: ExperimentConfig, comp: dict[str, Any], spec: Any) -> None:
    for method in spec.methods:
        rec = comp["methods"][method]
        assert len(rec["runs"]) == len(tiny.seeds), method
        assert sorted(r["seed"] for r in rec["runs"]) == sorted(tiny.seeds), method
        for run in rec["runs"]:
            ev = run["eval"]
            assert 0.0 <= ev["greedy_sr"] <= 1.0, method
            task = tiny.tasks[tiny.stages[method].tasks]
            if task.max_random_walk is not None:
                assert 0.0 <= ev["random_walk_sr"] <= TINY_RANDOM_WALK, method
            if task.max_blind is not None:
                assert 0.0 <= ev["blind_sr"] <= TINY_BLIND, method
                assert 0.0 <= ev["ablated_sr"] <= 1.0, method
            # budgets below 2 W: the training-SR rule cannot be met
            assert run["conv"]["censored"], method


def _check_units(tiny: ExperimentConfig, root: Path, part: str,
                 loaded_inits: dict[str, str]) -> None:
    for key in tiny.stages_for([part]):
        stage = tiny.stages[key]
        for seed in tiny.seeds:
            unit = root / "units" / key / f"seed-{seed}"
            result = read_result(unit)
            assert (result["mode"], result["algo"]) == (stage.mode, stage.algo), key
            assert Path(result["checkpoint"]).exists(), key
            if stage.init is None:
                assert str(unit) not in loaded_inits and "zero_shot" not in result["eval"], key
                continue
            # started from its parent's final checkpoint of the same seed (or from the final
            # checkpoint of its init_alt_m level)
            parent = read_result(root / "units" / stage.init / f"seed-{seed}")["checkpoint"]
            if stage.init_alt_m is not None:
                level = tiny.stages[stage.init].options.get("levels_m", (75.0, 45.0, 15.0))
                i = [float(a) for a in level].index(stage.init_alt_m)
                parent = str(Path(parent).parent.parent / f"stage_{i}_{stage.init_alt_m:g}m" /
                             "checkpoints" / "final.pt")
            assert result["eval"]["zero_shot"], key
            if stage.mode == "curriculum":
                state = json.loads((unit / "curriculum.json").read_text())
                assert state["init"] == parent, key
                assert [s["alt_m"] for s in state["stages"]] == \
                    list(tiny.tasks[stage.tasks].alts_m), key
                if stage.options.get("teacher", "kl") == "kl":
                    assert all(s["teacher"] for s in state["stages"][1:]), key
            else:
                assert loaded_inits[str(unit)] == parent, key
