"""The runner's packed groups (stage option ``pack = true``): the seeds of a stage in one
process, each member in its own unit folder, resumed from its own checkpoint."""

from __future__ import annotations

import csv
import json

from test_experiments_faults import _config, _episodes, _load, run_killing_once

from geonav.experiments.backend import LocalBackend
from geonav.experiments.runner import run_experiment


def _cfg(tmp_path, name, pack, episodes=40):
    path = _config(tmp_path, [dict(name="pre", episodes=episodes,
                                   extra=f"pack = {str(pack).lower()}")])
    path.write_text(path.read_text().replace('seeds = [0]', 'seeds = [0, 1]')
                    .replace('name = "faults"', f'name = "{name}"'))
    return _load(path)


def _returns(unit):
    with open(unit / "metrics.csv") as f:
        return [(int(r["episode"]), r["success"], r["length"]) for r in csv.DictReader(f)]


def test_packed_stage_equals_the_units_alone(tmp_path):
    root = tmp_path / "runs"
    packed = run_experiment(_cfg(tmp_path, "packed", True), root, backend=LocalBackend(1))
    alone = run_experiment(_cfg(tmp_path, "alone", False), root, backend=LocalBackend(1))
    assert packed["failed"] == {} and alone["failed"] == {}
    for seed in (0, 1):
        p = root / "packed" / "units" / "pre" / f"seed-{seed}"
        a = root / "alone" / "units" / "pre" / f"seed-{seed}"
        assert _returns(p) == _returns(a)
        rp, ra = (json.loads((d / "result.json").read_text()) for d in (p, a))
        assert rp["worker"]["packed_with"] == 2 and "packed_with" not in ra["worker"]
        assert rp["eval"]["greedy_sr"] == ra["eval"]["greedy_sr"]
        for f in ("config.json", "eval.csv", "checkpoints/final.pt", "checkpoints/latest.pt"):
            assert (p / f).exists(), f
    assert _returns(root / "packed" / "units" / "pre" / "seed-0") != \
        _returns(root / "packed" / "units" / "pre" / "seed-1")


def test_killed_packed_group_resumes_each_member_without_lost_or_duplicate_rows(tmp_path):
    cfg = _cfg(tmp_path, "faults", True, episodes=120)
    units = tmp_path / "runs" / "faults" / "units" / "pre"
    summary, killed = run_killing_once(cfg, tmp_path / "runs", units / "seed-0", 35)
    assert killed, "the group finished before it could be killed"
    assert summary["failed"] == {}
    for seed in (0, 1):
        unit = units / f"seed-{seed}"
        assert _episodes(unit / "metrics.csv") == list(range(1, 121))
        assert json.loads((unit / "retries.json").read_text())["worker_lost"] == 1
        result = json.loads((unit / "result.json").read_text())
        assert result["episodes"] == 120 and result["worker"]["pid"] != killed[0]
