"""The Ray backend on one local Ray cluster (127.0.0.1, 2 CPUs) started once for the session:
configs/tiny.toml gives the local backend's results, a killed worker is retried, a unit that
raises is reported, and a killed driver leaves nothing training on the cluster."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

# Before ray is imported (it reads them then): no usage reports, a single-node cluster on
# the loopback address only, and workers at the tests' own priority: at Ray's default
# niceness (15) a unit's imports took 25x longer while the cores were busy
# (bench/bench_ray_niceness.py), which made this module the suite's long pole.
RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
           "RAY_worker_niceness": "0"}
os.environ.update(RAY_ENV)

ray = pytest.importorskip("ray", reason="the Ray backend needs ray: pip install 'geonav[ray]'")

from proc_helpers import alive as _alive  # noqa: E402
from proc_helpers import tree as _tree  # noqa: E402

from geonav.experiments.backend import LocalBackend, RayBackend  # noqa: E402
from geonav.experiments.config import load_config  # noqa: E402
from geonav.experiments.runner import read_lock, run_experiment, unit_lock  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
TIMING = {"wall_s", "elapsed_s"}


@pytest.fixture(scope="module")
def ray_cluster():
    """One local Ray cluster for the session's Ray tests (only this module uses one), shut
    down after them so that it does not idle through the rest of the suite; yields its GCS
    address."""
    # one declared GPU: Ray only counts it (nothing here runs on it)
    ray.init(num_cpus=2, num_gpus=1, include_dashboard=False, _node_ip_address="127.0.0.1",
             log_to_driver=False)
    address = ray.get_runtime_context().gcs_address
    assert address.startswith("127.0.0.1:"), address
    yield address
    ray.shutdown()


def _metrics(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return [{k: v for k, v in row.items() if k not in TIMING} for row in csv.DictReader(f)]


def _untimed(v):
    """``v`` without its wall-clock figures (wall_*, compute_s)."""
    if isinstance(v, dict):
        return {k: _untimed(x) for k, x in v.items() if "wall" not in k and k != "compute_s"}
    if isinstance(v, list):
        return [_untimed(x) for x in v]
    if isinstance(v, float) and v != v:
        return "nan"  # NaN figures (an undefined ratio) compare equal
    return v


def _rows(path: Path) -> int:
    try:
        return max(0, len(path.read_text().splitlines()) - 1)
    except FileNotFoundError:
        return 0


def test_ray_runs_tiny_to_the_local_backends_results(tmp_path, ray_cluster):
    cfg = load_config(REPO / "configs" / "tiny.toml")
    local = run_experiment(cfg, tmp_path / "local", backend=LocalBackend(2))
    backend = RayBackend()
    assert backend.slots == 2  # 2 CPUs, 1 per unit (workers = 0)
    on_ray = run_experiment(cfg, tmp_path / "ray", backend=backend)
    assert on_ray["failed"] == local["failed"] == {}
    assert _untimed(on_ray["comparisons"]) == _untimed(local["comparisons"])
    for stage in ("pre", "transfer", "scratch"):
        a = tmp_path / "local" / "tiny" / "units" / stage / "seed-0"
        b = tmp_path / "ray" / "tiny" / "units" / stage / "seed-0"
        assert _metrics(a / "metrics.csv") == _metrics(b / "metrics.csv")
        ra, rb = (json.loads((d / "result.json").read_text()) for d in (a, b))
        assert ra["eval"] == rb["eval"] and ra["trajectories"] == rb["trajectories"]
        # written in place by the Ray worker (the folder is shared), not by this driver
        assert rb["worker"]["pid"] != os.getpid()
        assert rb["checkpoint"] == f"units/{stage}/seed-0/checkpoints/final.pt"
        assert (b / "checkpoints" / "final.pt").exists()
        assert (b / ".lock").read_text() == ""
    # rerun: everything is skipped, nothing is submitted to the cluster
    events = []
    again = run_experiment(cfg, tmp_path / "ray", backend=RayBackend(), report=False,
                           on_event=events.append)
    assert again["failed"] == {} and {e.status for e in events} == {"skipped"}


def test_ray_runs_a_packed_group_to_the_local_backends_results(tmp_path, ray_cluster):
    """A packed stage (two seeds in one process) is one Ray task, with the local results."""
    import tomllib

    from geonav.experiments.config import parse_config

    raw = tomllib.loads((REPO / "configs" / "tiny.toml").read_text())
    raw.update(name="tiny_packed", seeds=[0, 1], compare=[])
    raw["stages"] = {"scratch": {**raw["stages"]["scratch"], "episodes": 30, "pack": True}}
    cfg = parse_config(raw, "tiny_packed")
    local = run_experiment(cfg, tmp_path / "local", backend=LocalBackend(1), report=False)
    on_ray = run_experiment(cfg, tmp_path / "ray", backend=RayBackend(), report=False)
    assert on_ray["failed"] == local["failed"] == {}
    for seed in (0, 1):
        a = tmp_path / "local" / "tiny_packed" / "units" / "scratch" / f"seed-{seed}"
        b = tmp_path / "ray" / "tiny_packed" / "units" / "scratch" / f"seed-{seed}"
        assert _metrics(a / "metrics.csv") == _metrics(b / "metrics.csv")
        ra, rb = (json.loads((d / "result.json").read_text()) for d in (a, b))
        assert ra["eval"] == rb["eval"]
        assert rb["worker"]["packed_with"] == 2 and rb["worker"]["pid"] != os.getpid()
    pids = {json.loads((tmp_path / "ray" / "tiny_packed" / "units" / "scratch" /
                        f"seed-{s}" / "result.json").read_text())["worker"]["pid"]
            for s in (0, 1)}
    assert len(pids) == 1  # one task for the group


def test_unreachable_address_is_one_line(tmp_path):
    # no cluster needed: nothing listens on port 1 of the loopback address
    r = subprocess.run([sys.executable, "-m", "geonav.cli", "experiment", "run",
                        str(REPO / "configs" / "tiny.toml"), "--address", "127.0.0.1:1"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**os.environ, **RAY_ENV})
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith(
        "geonav: error: no Ray cluster answers at 127.0.0.1:1:")
    assert not (tmp_path / "runs").exists()


def test_units_reserve_the_gpus_asked_for(ray_cluster):
    backend = RayBackend(gpus_per_unit=1)
    assert backend.slots == 1  # 2 CPUs but 1 GPU
    assert backend.submit(os.getenv, "CUDA_VISIBLE_DEVICES").result(timeout=120) == "0"
    assert RayBackend(gpus_per_unit=0.5).slots == 2


def test_run_folder_must_be_shared_with_every_node(tmp_path, ray_cluster):
    from geonav.experiments.backend import _probe_folder

    backend = RayBackend()
    backend.check_run_folder(tmp_path)  # every node (this one) sees it
    assert not list(tmp_path.glob(".ray-probe-*"))
    probe = ray.remote(num_cpus=0)(_probe_folder)
    seen = ray.get(probe.remote(str(tmp_path / "elsewhere" / ".ray-probe-x"), "token"))
    assert seen["ok"] is False and seen["host"]  # what a node without the folder answers


def test_killed_ray_worker_is_retried_and_a_failing_unit_is_reported(tmp_path, ray_cluster):
    text = (REPO / "configs" / "tiny.toml").read_text().split("[stages.pre]")[0]
    text = text.replace('name = "tiny"', 'name = "faults"')
    text += """
[stages.pre]
mode = "train"
tasks = "A_meta"
algo = "a3c"
episodes = 300
workers = 0
checkpoint_every = 10

[stages.bad]
mode = "train"
tasks = "A_meta"
algo = "a3c"
episodes = 20
workers = 0
engine = "async"
device = "cuda"
"""
    (tmp_path / "faults.toml").write_text(text)
    cfg = load_config(tmp_path / "faults.toml")
    unit = tmp_path / "runs" / "faults" / "units" / "pre" / "seed-0"
    stop, killed = threading.Event(), []

    def kill_once() -> None:
        while not stop.is_set() and not killed:
            lock = read_lock(unit)
            if lock and (unit / "checkpoints" / "latest.pt").exists() and \
                    _rows(unit / "metrics.csv") >= 35:
                os.kill(int(lock["pid"]), signal.SIGKILL)
                killed.append(int(lock["pid"]))
            time.sleep(0.005)

    watcher = threading.Thread(target=kill_once)
    watcher.start()
    try:
        summary = run_experiment(cfg, tmp_path / "runs", backend=RayBackend(), max_retries=2,
                                 report=False)
    finally:
        stop.set()
        watcher.join()
    assert killed, "the unit finished before it could be killed"
    assert summary["retries"] == {"pre/seed-0": 1}
    assert list(summary["failed"]) == ["bad/seed-0"]
    assert summary["failed"]["bad/seed-0"].startswith("ConfigError: the async engine runs on "
                                                      "the CPU")
    trace = (unit.parent.parent / "bad" / "seed-0" / "error.txt").read_text()
    assert "Traceback" in trace and "device 'cuda' needs engine = 'batched'" in trace
    episodes = [int(r["episode"]) for r in _metrics(unit / "metrics.csv")]
    assert episodes == list(range(1, 301))  # nothing lost, nothing twice
    resumed = json.loads((unit / "config.json").read_text())
    assert resumed["resume"] and resumed["start_episode"] >= 30
    result = json.loads((unit / "result.json").read_text())
    assert result["episodes"] == 300 and result["worker"]["pid"] != killed[0]


def test_killed_driver_leaves_nothing_running_on_the_cluster(tmp_path, ray_cluster):
    # long units, each with an A3C worker process of its own (no comparison: no budget
    # check of the convergence rule)
    text = (REPO / "configs" / "tiny.toml").read_text().split("[[compare]]")[0].replace(
        "episodes = 60", "episodes = 50000").replace("workers = 0",
                                                      'workers = 1\nengine = "async"')
    (tmp_path / "long.toml").write_text(text)
    env = {**os.environ, **RAY_ENV}
    log = (tmp_path / "driver.log").open("w")
    driver = subprocess.Popen(
        [sys.executable, "-m", "geonav.cli", "experiment", "run", str(tmp_path / "long.toml"),
         "--out", "runs", "--address", ray_cluster, "--fly", "no"],
        cwd=tmp_path, env=env, stdout=log, stderr=log, start_new_session=True)
    units = tmp_path / "runs" / "tiny" / "units"
    try:
        deadline, pids = time.time() + 120, {}
        while time.time() < deadline and driver.poll() is None and len(pids) < 2:
            for stage in ("pre", "scratch"):
                lock = read_lock(units / stage / "seed-0")
                if lock and _rows(units / stage / "seed-0" / "metrics.csv") > 5:
                    pids[stage] = int(lock["pid"])
            time.sleep(0.2)
        assert len(pids) == 2, (tmp_path / "driver.log").read_text()[-3000:]
        procs = sorted({p for pid in pids.values() for p in _tree(pid)})
        assert len(procs) >= 4, procs  # two Ray workers and their A3C workers
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait()
        deadline = time.time() + 30
        while time.time() < deadline and any(_alive(p) for p in procs):
            time.sleep(0.2)
        assert not [p for p in procs if _alive(p)], "units outlived their driver"
        for stage in pids:  # the units' folders are free for a rerun
            with unit_lock(units / stage / "seed-0"):
                pass
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
        log.close()


