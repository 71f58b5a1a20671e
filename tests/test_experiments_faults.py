"""Faults of the local experiment backend: unit locks, workers that outlive a killed runner,
retries of a unit whose worker died, units that raise, and sweeps (real training, seconds)."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from proc_helpers import alive as _alive
from proc_helpers import tree as _tree

from geonav.errors import ConfigError
from geonav.experiments.backend import LocalBackend
from geonav.experiments.config import parse_config
from geonav.experiments.runner import UnitLocked, read_lock, run_experiment, unit_lock
from geonav.experiments.sweep import parse_param, run_sweep, sweep_configs

BASE = """
name = "faults"
seeds = [0]
eval_starts = 4

[convergence]
window = 20
threshold = 0.9
hold = 0.8

[scenes.A]
synthetic = "residential"
size_m = 300.0
gsd_m = 1.0

[tasks.A_meta]
scene = "A"
kind = "meta"
count = 1
size_m = 45.0
alt_m = 60.0
step_m = 15.0
max_steps = 15
obs_size_px = 24
"""

STAGE = """
[stages.{name}]
mode = "train"
tasks = "A_meta"
algo = "a3c"
episodes = {episodes}
workers = {workers}
lr = 0.001
checkpoint_every = 10
{extra}
"""


def _config(tmp_path: Path, stages: list[dict], compare: list[str] | None = None) -> Path:
    text = BASE + "".join(STAGE.format(**{"workers": 0, "extra": "", **s}) for s in stages)
    if compare:
        text += f'\n[[compare]]\nname = "c"\nmethods = {json.dumps(compare)}\n'
    path = tmp_path / "faults.toml"
    path.write_text(text)
    return path


def _load(path: Path):
    import tomllib

    return parse_config(tomllib.loads(path.read_text()), str(path))




def _episodes(metrics: Path) -> list[int]:
    rows = metrics.read_text().strip().splitlines()[1:]
    return [int(r.split(",")[0]) for r in rows]


def _rows(metrics: Path) -> int:
    try:
        return max(0, len(metrics.read_text().splitlines()) - 1)
    except FileNotFoundError:
        return 0


def test_unit_lock_refuses_a_live_holder_and_takes_over_a_dead_ones(tmp_path, caplog):
    unit = tmp_path / "units" / "pre" / "seed-0"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path; "
         "from geonav.experiments.runner import unit_lock\n"
         f"with unit_lock(Path({str(unit)!r})):\n    print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert read_lock(unit)["pid"] == holder.pid
        with pytest.raises(UnitLocked, match=f'"pid": {holder.pid}'), \
                unit_lock(unit, wait_s=0.3):
            pass
        # SIGKILL: no cleanup runs, the record stays, the kernel drops the flock
        holder.kill()
        holder.wait()
    finally:
        holder.kill()
    assert read_lock(unit)["pid"] == holder.pid
    with caplog.at_level(logging.WARNING, "geonav.experiments.runner"), unit_lock(unit):
        assert read_lock(unit)["pid"] == os.getpid()
    assert f"pid {holder.pid} is not running" in caplog.text
    assert "stale lock" in caplog.text
    assert (unit / ".lock").read_text() == ""  # a clean release leaves nothing stale
    # a lock is per holder: a second holder in the same process is refused too
    with unit_lock(unit), pytest.raises(UnitLocked, match=socket.gethostname()), \
            unit_lock(unit, wait_s=0):
        pass
    # a holder that is on its way out is waited for
    quitting = subprocess.Popen(
        [sys.executable, "-c", "import time; from pathlib import Path; "
         "from geonav.experiments.runner import unit_lock\n"
         f"with unit_lock(Path({str(unit)!r})):\n    print('held', flush=True); time.sleep(1)\n"
         "print('released', flush=True)"],
        stdout=subprocess.PIPE, text=True)
    assert quitting.stdout.readline().strip() == "held"
    with unit_lock(unit, wait_s=30):  # refused at first, then taken
        assert read_lock(unit)["pid"] == os.getpid()
    assert quitting.stdout.readline().strip() == "released"
    quitting.wait()


def test_runner_refused_by_a_live_runs_lock_leaves_its_report_alone(tmp_path):
    """A second runner of the same experiment, refused by the unit locks of the live one,
    does not rewrite report.md and summary.json with false "Failed units": the live run
    writes them when it ends."""
    cfg = _load(_config(tmp_path, [dict(name="pre", episodes=20),
                                   dict(name="after", episodes=20, extra='init = "pre"')]))
    root = tmp_path / "runs" / "faults"
    unit = root / "units" / "pre" / "seed-0"
    root.mkdir(parents=True)
    (root / "config.json").write_text(json.dumps(cfg.to_dict()))  # as the live run wrote it
    holder = subprocess.Popen(
        [sys.executable, "-c", "import time; from pathlib import Path; "
         "from geonav.experiments.runner import unit_lock\n"
         f"with unit_lock(Path({str(unit)!r})):\n    print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        (root / "report.md").write_text("the live run's report\n")
        (root / "summary.json").write_text('{"name": "faults", "live": true}')
        summary = run_experiment(cfg, tmp_path / "runs", backend=LocalBackend(1))
    finally:
        holder.kill()
        holder.wait()
    assert list(summary["locked"]) == ["pre/seed-0"]
    assert f'"pid": {holder.pid}' in summary["locked"]["pre/seed-0"]
    assert summary["failed"]["after/seed-0"] == "parent pre/seed-0 is being trained by " \
        "another run"
    assert (root / "report.md").read_text() == "the live run's report\n"
    assert json.loads((root / "summary.json").read_text()) == {"name": "faults", "live": True}
    assert not (unit / "result.json").exists()


def test_sigkilled_runner_leaves_no_worker_alive(tmp_path):
    # two long units, one of them with an A3C worker process of its own (a grandchild)
    cfg = _config(tmp_path, [dict(name="solo", episodes=20000),
                             dict(name="multi", episodes=20000, workers=1,
                                  extra='engine = "async"')])
    root = tmp_path / "runs" / "faults"
    proc = subprocess.Popen([sys.executable, "-m", "geonav.cli", "experiment", "run", str(cfg),
                             "--out", "runs", "--jobs", "2", "--fly", "no"], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.time() + 120
        locks: dict[str, int] = {}
        while time.time() < deadline and proc.poll() is None:
            for name in ("solo", "multi"):
                unit = root / "units" / name / "seed-0"
                lock = read_lock(unit)
                if lock and _rows(unit / "metrics.csv") > 5:
                    locks[name] = int(lock["pid"])
            if len(locks) == 2:
                break
            time.sleep(0.2)
        assert len(locks) == 2, "the units did not start training in time"
        workers = sorted(locks.values())
        assert proc.pid not in workers
        procs = sorted({p for w in workers for p in _tree(w)})
        assert len(procs) >= 3, procs  # two unit workers and the A3C worker of "multi"
        os.kill(proc.pid, signal.SIGKILL)  # the runner only, not its process group
        proc.wait()
        deadline = time.time() + 15
        while time.time() < deadline and any(_alive(p) for p in procs):
            time.sleep(0.1)
        assert not [p for p in procs if _alive(p)], "workers outlived the killed runner"
        # their locks went with them: a rerun may take the units over
        with unit_lock(root / "units" / "solo" / "seed-0"):
            pass
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        for p in locals().get("procs", []):
            try:
                os.kill(p, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _kill_once_mid_run(unit: Path, after_rows: int, stop: threading.Event) -> list[int]:
    """Kill the process that holds ``unit``'s lock once it has logged ``after_rows`` rows
    past a checkpoint; returns the killed pid(s)."""
    killed: list[int] = []
    while not stop.is_set() and not killed:
        lock = read_lock(unit)
        if lock and (unit / "checkpoints" / "latest.pt").exists() and \
                _rows(unit / "metrics.csv") >= after_rows:
            os.kill(int(lock["pid"]), signal.SIGKILL)
            killed.append(int(lock["pid"]))
        time.sleep(0.005)
    return killed


def run_killing_once(cfg, runs: Path, unit: Path, after_rows: int):
    """Run ``cfg`` on one local slot (max_retries 1) while the holder of ``unit``'s lock is
    killed once mid-run; (summary, killed pids)."""
    stop = threading.Event()
    killed: list[int] = []
    watcher = threading.Thread(
        target=lambda: killed.extend(_kill_once_mid_run(unit, after_rows, stop)))
    watcher.start()
    try:
        summary = run_experiment(cfg, runs, backend=LocalBackend(1), max_retries=1)
    finally:
        stop.set()
        watcher.join()
    return summary, killed


def test_dead_worker_is_retried_from_its_checkpoint_without_lost_or_duplicate_rows(tmp_path):
    cfg = _load(_config(tmp_path, [dict(name="pre", episodes=120)]))
    unit = tmp_path / "runs" / "faults" / "units" / "pre" / "seed-0"
    summary, killed = run_killing_once(cfg, tmp_path / "runs", unit, 35)
    assert killed, "the unit finished before it could be killed"
    assert summary["failed"] == {} and summary["retries"] == {"pre/seed-0": 1}
    written = json.loads((unit.parent.parent.parent / "summary.json").read_text())
    assert written["retries"] == {"pre/seed-0": 1} and written["name"] == "faults"
    assert json.loads((unit / "retries.json").read_text())["worker_lost"] == 1
    resumed = json.loads((unit / "config.json").read_text())
    assert resumed["resume"] and resumed["start_episode"] >= 30
    assert _episodes(unit / "metrics.csv") == list(range(1, 121))
    result = json.loads((unit / "result.json").read_text())
    assert result["episodes"] == 120 and result["worker"]["pid"] != killed[0]


def test_dead_worker_beyond_max_retries_fails_the_unit(tmp_path):
    cfg = _load(_config(tmp_path, [dict(name="pre", episodes=400)]))
    unit = tmp_path / "runs" / "faults" / "units" / "pre" / "seed-0"
    stop = threading.Event()
    watcher = threading.Thread(target=_kill_once_mid_run, args=(unit, 12, stop))
    watcher.start()
    try:
        summary = run_experiment(cfg, tmp_path / "runs", backend=LocalBackend(1),
                                 max_retries=0, report=False)
    finally:
        stop.set()
        watcher.join()
    assert "died 1 times (max_retries = 0)" in summary["failed"]["pre/seed-0"]
    assert not (unit / "result.json").exists()


def test_unit_that_raises_is_reported_with_its_traceback_and_the_rest_goes_on(tmp_path):
    cfg = _load(_config(tmp_path, [dict(name="good", episodes=20),
                                   # passes the config's checks, raises when it runs
                                   dict(name="bad", episodes=20,
                                        extra='engine = "async"\ndevice = "cuda"'),
                                   dict(name="after_bad", episodes=20, extra='init = "bad"')],
                        compare=["good", "after_bad"]))
    summary = run_experiment(cfg, tmp_path / "runs", backend=LocalBackend(1))
    root = tmp_path / "runs" / "faults"
    assert sorted(summary["failed"]) == ["after_bad/seed-0", "bad/seed-0"]
    assert summary["failed"]["bad/seed-0"].startswith("ConfigError: the async engine runs "
                                                      "on the CPU")
    assert summary["failed"]["after_bad/seed-0"] == "parent bad/seed-0 failed"
    trace = (root / "units" / "bad" / "seed-0" / "error.txt").read_text()
    assert trace.startswith("Traceback")
    assert "ConfigError: the async engine runs on the CPU; device 'cuda'" in trace
    assert json.loads((root / "units/good/seed-0/result.json").read_text())["episodes"] == 20
    assert "## Failed units" in (root / "report.md").read_text()


def test_sweep_runs_a_grid_through_one_backend_with_one_table(tmp_path):
    cfg = _config(tmp_path, [dict(name="pre", episodes=20),
                             dict(name="tune", episodes=30, extra='init = "pre"')],
                  compare=["tune"])
    record = run_sweep(cfg, ["stages.tune.lr=1e-3,1e-2", "stages.tune.max_grad_norm=20.0"],
                       tmp_path / "runs", overrides={"seeds": [0, 1]},
                       backend=LocalBackend(0))
    folder = tmp_path / "runs" / "faults-sweep"
    assert record["folder"] == str(folder)
    assert [(r["stages.tune.lr"], r["method"], r["n"]) for r in record["rows"]] == \
        [(0.001, "tune", 2), (0.01, "tune", 2)]
    variants = sorted(p.name for p in folder.iterdir() if p.is_dir() and p.name != "inputs")
    assert variants == ["lr=0.001,max_grad_norm=20.0", "lr=0.01,max_grad_norm=20.0"]
    # the points share one copy of their (identical) scene and task set ...
    assert len(list((folder / "inputs" / "scenes").iterdir())) == 1
    assert len(list((folder / "inputs" / "tasks").glob("*.json"))) == 1
    assert not (folder / variants[0] / "scenes").exists()
    # ... and train their identical parent stage once: the second point links to the first's
    for seed in (0, 1):
        first, second = (folder / v / f"units/pre/seed-{seed}" for v in variants)
        assert not first.is_symlink() and second.is_symlink()
        assert second.resolve() == first.resolve()
        for v, lr in zip(variants, (0.001, 0.01), strict=True):
            run = json.loads((folder / v / f"units/tune/seed-{seed}/config.json").read_text())
            a3c = run["a3c"]
            assert (a3c["lr"], a3c["max_grad_norm"], a3c["seed"]) == (lr, 20.0, seed)
            assert _episodes(folder / v / f"units/tune/seed-{seed}/metrics.csv") == \
                list(range(1, 31))
    table = (folder / "sweep.md").read_text()
    assert "| stages.tune.lr | stages.tune.max_grad_norm | comparison | method |" in table
    assert "| 0.001 | 20.0 | c | tune |" in table and "| 0.01 | 20.0 | c | tune |" in table
    assert "| e* training SR (median) | censored | e* greedy eval (median) | censored | " \
        "final greedy SR (median) |" in table
    for r in record["rows"]:  # what each point's report says, not n/a
        assert 0.0 <= r["final_greedy_sr"] <= 1.0 and r["eval_n"] == 2
        assert r["median_episodes"] is not None and r["eval_median_episodes"] is not None
    assert json.loads((folder / "sweep.json").read_text())["rows"] == record["rows"]
    # resume: a rerun finds every unit done, shared ones through their links
    events = []
    again = run_sweep(cfg, ["stages.tune.lr=1e-3,1e-2", "stages.tune.max_grad_norm=20.0"],
                      tmp_path / "runs", overrides={"seeds": [0, 1]},
                      backend=LocalBackend(0), on_event=events.append)
    assert {e.status for e in events} == {"skipped"} and len(events) == 8
    assert again["rows"] == record["rows"]


def test_sweep_params_and_backend_table():
    assert parse_param("stages.a.alpha=1e-3,1e-2, 0.1") == ("stages.a.alpha", [0.001, 0.01, 0.1])
    assert parse_param("stages.a.algo=isar,savn") == ("stages.a.algo", ["isar", "savn"])
    assert parse_param("stages.a.stop_at_convergence=true") == \
        ("stages.a.stop_at_convergence", [True])
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_param("stages.a.alpha")
    with pytest.raises(ConfigError, match="names its variants"):
        parse_param("name=x,y")
    base = {"scenes": {"A": {"synthetic": "residential"}}, "tasks": {"t": {"scene": "A"}},
            "stages": {"s": {"mode": "train", "tasks": "t"}}}
    spec = parse_config({**base, "backend": {"kind": "ray", "address": "auto",
                                             "gpus_per_unit": 0.5}}).backend
    assert (spec.kind, spec.address, spec.gpus_per_unit, spec.max_retries) == \
        ("ray", "auto", 0.5, 2)
    assert parse_config(base).backend.kind == "local"
    with pytest.raises(ConfigError, match=r"\[backend\] kind = 'slurm'"):
        parse_config({**base, "backend": {"kind": "slurm"}})
    with pytest.raises(ConfigError, match=r"\[backend\]: unknown key"):
        parse_config({**base, "backend": {"nodes": 3}})
    with pytest.raises(ConfigError, match=r"\[backend\] max_retries = 'two': expected int"):
        parse_config({**base, "backend": {"max_retries": "two"}})
    with pytest.raises(ConfigError, match="gpus_per_unit needs kind"):
        parse_config({**base, "backend": {"gpus_per_unit": 1}})


def test_sweep_key_must_name_a_table(tmp_path):
    cfg = _config(tmp_path, [dict(name="pre", episodes=30)])
    with pytest.raises(ConfigError, match=r"\[stages.nope\] is not a table"):
        sweep_configs(cfg, ["stages.nope.lr=1,2"])
    name, variants = sweep_configs(cfg, ["stages.pre.lr=1e-3,1e-2"])
    assert name == "faults-sweep"
    assert [c.name for _, c in variants] == ["faults-sweep/lr=0.001", "faults-sweep/lr=0.01"]
    assert [c.stages["pre"].options["lr"] for _, c in variants] == [0.001, 0.01]


def _cli(cwd: Path, *args: str, pre: str = "") -> subprocess.CompletedProcess:
    code = f"import sys\n{pre}\nfrom geonav.cli import main\nsys.exit(main({list(args)!r}))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, cwd=cwd)


def test_cli_backend_options_fail_in_one_line(tmp_path):
    tiny = str(Path(__file__).resolve().parent.parent / "configs" / "tiny.toml")
    r = _cli(tmp_path, "experiment", "run", tiny, "--backend", "local", "--address", "auto")
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == \
        "geonav: error: --address names a Ray cluster: use it with --backend ray"
    # without the extra, --backend ray names it (ray hidden from the import system)
    r = _cli(tmp_path, "experiment", "sweep", tiny, "--param", "stages.pre.lr=1e-3",
             "--backend", "ray", pre="sys.modules['ray'] = None")
    assert r.returncode == 2
    assert "pip install 'geonav[ray]'" in r.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "runs").exists()  # it stopped before making anything


def _fork_and_terminate_a_child() -> dict:
    pid = os.fork()
    if pid == 0:  # like an A3C worker: forked from the unit's process, stopped by SIGTERM
        time.sleep(30)
        os._exit(0)
    time.sleep(0.2)
    os.kill(pid, signal.SIGTERM)
    _, status = os.waitpid(pid, 0)
    return {"signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) else None,
            "pid": os.getpid(), "pgid": os.getpgrp()}


def test_local_worker_survives_the_sigterm_of_a_child_it_forked():
    backend = LocalBackend(1)
    try:
        r = backend.submit(_fork_and_terminate_a_child).result(timeout=120)
    finally:
        backend.shutdown()
    assert r["pgid"] == r["pid"]  # the worker leads its own process group
    assert r["signal"] == signal.SIGTERM  # the child alone ended, as by default


def test_resumed_unit_convergence_stop_sees_no_evaluation_after_the_checkpoint(
        tmp_path, monkeypatch):
    """stop_at_convergence on resume: the evaluations logged after the checkpoint are
    dropped before the stop rule reads eval.csv (they are run again)."""
    import shutil

    from geonav.experiments import stages
    from geonav.testing import textured_scene, tiny_taskset

    scene = textured_scene(size_m=300.0)
    scene.save(tmp_path / "scene")
    tiny_taskset(scene, max_steps=10).save(tmp_path / "tasks.json")
    seen = []

    class Recording(stages.ConvergenceStop):
        def on_train_end(self, result):
            seen.append([e for e, _ in self.evals])

    monkeypatch.setattr(stages, "ConvergenceStop", Recording)
    out = tmp_path / "unit"
    p = dict(stage="s", mode="train", algo="a3c", episodes=8, workers=0, seed=0,
             scene=str(tmp_path / "scene"), tasks=str(tmp_path / "tasks.json"),
             init_checkpoint=None, out_dir=str(out), eval_starts=3,
             convergence=dict(window=50, threshold=0.99, hold=0.99, eval_threshold=1.0),
             options=dict(encoder="random", batch=2, eval_every=2,
                          checkpoint_every=4, keep_checkpoints=True, eval_max_starts=3,
                          stop_at_convergence=True))
    stages.execute_stage(p)
    shutil.copy(out / "checkpoints" / "episode_4.pt", out / "checkpoints" / "latest.pt")
    stages.execute_stage(p)
    assert seen == [[2, 4, 6, 8], [2, 4, 6, 8]]
