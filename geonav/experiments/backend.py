"""Where units of work run: the scheduling seam of the experiment runner.

A unit (one stage for one seed) is a picklable call ``fn(*args) -> dict``. The
runner only needs :class:`Backend`: ``attach`` sees the run folder once,
``submit`` returns a :class:`concurrent.futures.Future`, ``shutdown`` stops.

* :class:`LocalBackend` runs each unit in a spawned local worker process (one
  single-worker pool per slot). A worker is the leader of its own process
  group and dies, with everything it started, when the runner dies
  (``PR_SET_PDEATHSIG`` on Linux, plus a parent-pid poll everywhere), so a
  SIGKILLed runner leaves nothing training.
* :class:`RayBackend` runs each unit as a Ray task (``num_cpus`` from the
  stage's workers, ``num_gpus`` when asked; Ray reuses its worker processes
  between units as the local pool does). The run folder must be on a
  filesystem that every Ray node sees at the same absolute path: workers
  write checkpoints, metrics and ``result.json`` straight into it, the driver
  only the config, inputs and report; ``attach`` checks the folder from every
  node. Tasks belong to the driver: when it dies, Ray stops them.

A unit whose process dies (killed, out of memory, node lost) fails its future
with :class:`WorkerLost`; the runner retries it from its last checkpoint.
Any other exception is the unit's own failure and is reported, not retried.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import os
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any, Protocol

from geonav.errors import ConfigError, GeonavError, MissingExtra

log = logging.getLogger(__name__)

PARENT_POLL_S = 0.5
"""How often a local worker checks that its parent (the runner) is still alive."""


class WorkerLost(GeonavError):
    """The process (or node) running a unit died; the unit can be retried."""


class BackendError(GeonavError):
    """A backend cannot run units (no cluster, run folder not shared, ...)."""


class Backend(Protocol):
    """Runs independent units of work."""

    slots: int
    """How many units may run at once."""

    def attach(self, root: Path) -> None:
        """Called once with the run folder before any unit is submitted."""

    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any,
               resources: dict[str, float] | None = None) -> Future:
        """Start ``fn(*args)``; the future's result is the unit's result dict.

        ``resources``: ``{"cpus": n, "gpus": m}`` the unit needs (a hint; local ignores it).
        """

    def shutdown(self, cancel: bool = False) -> None:
        """Release the workers; ``cancel`` stops running and queued units."""


# --- local processes -------------------------------------------------------------------------

def _set_parent_death_signal(sig: int) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent thread exits."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        return libc.prctl(pr_set_pdeathsig, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _kill_own_group(*_: Any) -> None:
    # This worker leads its process group: the trainer's own worker processes go too.
    os.killpg(os.getpgrp(), signal.SIGKILL)


def _on_sigterm(signum: int, frame: Any) -> None:
    if os.getpid() == os.getpgrp():
        _kill_own_group()
    # a process forked from the worker (an A3C worker) inherited this handler: a SIGTERM
    # meant for it alone (its trainer stopping it) ends it alone, as by default
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.kill(os.getpid(), signal.SIGTERM)


def _watch_parent(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            _kill_own_group()
        time.sleep(PARENT_POLL_S)


def _worker_init(parent_pid: int) -> None:
    """Initializer of a local worker: own process group, exit when the runner dies."""
    os.setpgrp()
    signal.signal(signal.SIGTERM, _on_sigterm)
    _set_parent_death_signal(signal.SIGTERM)
    if os.getppid() != parent_pid:  # the runner died before prctl took effect
        _kill_own_group()
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True,
                     name="geonav-parent-watch").start()


class _Slot:
    """One single-worker spawn pool: a crash takes down only its own unit."""

    def __init__(self) -> None:
        self.pool = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"),
                                        initializer=_worker_init, initargs=(os.getpid(),))
        self.future: Future | None = None

    def free(self) -> bool:
        return self.future is None or self.future.done()

    def pids(self) -> list[int]:
        return list(getattr(self.pool, "_processes", None) or {})

    def close(self, cancel: bool) -> None:
        pids = self.pids()
        self.pool.shutdown(wait=not cancel, cancel_futures=cancel)
        if cancel:
            for pid in pids:
                _kill_group(pid)


def _kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


class LocalBackend:
    """Units in up to ``jobs`` local processes (spawned: each gets a clean torch state).

    Args:
        jobs: concurrent units; 0 runs units inline in a thread of this process (tests).
    """

    def __init__(self, jobs: int = 1) -> None:
        self.slots = max(1, jobs)
        self._threads: ThreadPoolExecutor | None = ThreadPoolExecutor(1) if jobs <= 0 else None
        self._slots: list[_Slot] = []
        self._lock = threading.Lock()

    def attach(self, root: Path) -> None:
        pass

    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any,
               resources: dict[str, float] | None = None) -> Future:
        if self._threads is not None:
            return self._threads.submit(fn, *args)
        with self._lock:
            slot = next((s for s in self._slots if s.free()), None)
            if slot is None:
                slot = _Slot()
                self._slots.append(slot)
            out: Future = Future()
            try:
                inner = slot.pool.submit(fn, *args)
            except BrokenProcessPool:
                self._replace(slot)
                slot = self._slots[-1]
                inner = slot.pool.submit(fn, *args)
            slot.future = out
            pids = slot.pids()
            inner.add_done_callback(lambda f: self._settle(slot, pids, f, out))
            return out

    def _replace(self, slot: _Slot) -> None:
        self._slots.remove(slot)
        slot.close(cancel=True)
        self._slots.append(_Slot())

    def _settle(self, slot: _Slot, pids: list[int], inner: Future, out: Future) -> None:
        if inner.cancelled():  # dropped by shutdown(cancel=True) before it started
            out.cancel()
            return
        exc = inner.exception()
        if isinstance(exc, BrokenProcessPool):
            for pid in pids:  # whatever the dead worker had started
                _kill_group(pid)
            with self._lock:
                if slot in self._slots:
                    self._replace(slot)
            out.set_exception(WorkerLost(f"the local worker process {pids} died: {exc}"))
        elif exc is not None:
            out.set_exception(exc)
        else:
            out.set_result(inner.result())

    def shutdown(self, cancel: bool = False) -> None:
        if self._threads is not None:
            self._threads.shutdown(wait=not cancel, cancel_futures=cancel)
        with self._lock:
            slots, self._slots = self._slots, []
        for s in slots:
            s.close(cancel)


# --- Ray ---------------------------------------------------------------------------------------

def _import_ray() -> Any:
    try:
        import ray
    except ImportError as err:
        raise MissingExtra("ray", "ray", "the Ray experiment backend") from err
    return ray


def _check_reachable(address: str | None, timeout_s: float = 10.0) -> None:
    """Fail fast on a ``HOST:PORT`` address nothing listens at (Ray itself retries for
    minutes)."""
    if not address or address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise BackendError(f"Ray address {address!r}: use auto, ray://HOST:10001 or HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as err:
        raise BackendError(f"no Ray cluster answers at {address}: {err}; start one with "
                           "`ray start --head` (or `ray up`), or pass its address") from err


def _probe_folder(path: str, token: str) -> dict[str, Any]:
    """Runs on a Ray node: does it see ``path`` with the driver's token inside?"""
    p = Path(path)
    try:
        seen = p.read_text().strip()
    except OSError:
        seen = None
    return {"host": socket.gethostname(), "ok": seen == token, "path": path}


class RayBackend:
    """Units as Ray tasks on a cluster (``ray.init(address=...)``).

    Args:
        address: ``auto`` (a cluster started with ``ray start`` on this machine or the
            one this driver runs in), ``ray://HOST:10001`` (Ray Client), ``HOST:6379``
            (the GCS of a reachable head), or None (attach to a running ``ray.init``, or
            start a local one).
        cpus_per_unit: CPUs a unit reserves; None: ``max(1, stage workers)``.
        gpus_per_unit: GPUs a unit reserves (fractions allowed).
        max_units: cap on concurrent units; None: as many as the cluster's CPUs (and GPUs,
            with ``gpus_per_unit``) hold at start.
        runtime_env: passed to the tasks (``env_vars``, ``pip``, ...).
        check_shared: probe from every node that the run folder is shared.
    """

    def __init__(self, address: str | None = None, *, cpus_per_unit: float | None = None,
                 gpus_per_unit: float = 0.0, max_units: int | None = None,
                 runtime_env: dict[str, Any] | None = None, check_shared: bool = True) -> None:
        ray = _import_ray()
        self._ray = ray
        self._owns = False
        if not ray.is_initialized():
            _check_reachable(address)
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as err:
                raise BackendError(f"cannot connect to the Ray cluster at {address!r}: {err}; "
                                   "start one with `ray start --head` (or `ray up`) or pass "
                                   "--address") from err
            self._owns = True
        self.cpus_per_unit = cpus_per_unit
        self.gpus_per_unit = float(gpus_per_unit)
        self.runtime_env = runtime_env
        self.check_shared = check_shared
        have = ray.cluster_resources()
        fit = int(float(have.get("CPU", 1.0)) // float(cpus_per_unit or 1.0))
        if self.gpus_per_unit > 0:
            fit = min(fit, int(float(have.get("GPU", 0.0)) // self.gpus_per_unit))
        self.slots = max(1, fit) if max_units is None else max(1, int(max_units))
        self._refs: dict[Any, Future] = {}
        self._remotes: dict[Callable[..., Any], Any] = {}
        self._lock = threading.Lock()

    def attach(self, root: Path) -> None:
        if self.check_shared:
            self.check_run_folder(root)

    def check_run_folder(self, root: Path) -> None:
        """Raise :class:`BackendError` unless every alive node sees ``root``."""
        ray = self._ray
        token = uuid.uuid4().hex
        probe = Path(root) / f".ray-probe-{token[:8]}"
        probe.write_text(token)
        try:
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            nodes = [n["NodeID"] for n in ray.nodes() if n.get("Alive")]
            fn = ray.remote(num_cpus=0)(_probe_folder)
            refs = [fn.options(scheduling_strategy=NodeAffinitySchedulingStrategy(
                n, soft=False)).remote(str(probe), token) for n in nodes]
            answers = ray.get(refs, timeout=120)
        finally:
            probe.unlink(missing_ok=True)
        bad = [a["host"] for a in answers if not a["ok"]]
        if bad:
            raise BackendError(f"the run folder {root} is not visible on Ray node(s) {bad}: "
                               "put --out on a filesystem shared by every node at the same "
                               "path (NFS, EFS, a ReadWriteMany volume in KubeRay)")

    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any,
               resources: dict[str, float] | None = None) -> Future:
        ray = self._ray
        res = resources or {}
        cpus = self.cpus_per_unit if self.cpus_per_unit is not None else res.get("cpus", 1)
        options: dict[str, Any] = dict(num_cpus=float(cpus), num_gpus=self.gpus_per_unit,
                                       max_retries=0)
        if self.runtime_env:
            options["runtime_env"] = self.runtime_env
        remote = self._remotes.get(fn)
        if remote is None:
            remote = self._remotes[fn] = ray.remote(fn)
        ref = remote.options(**options).remote(*args)
        out: Future = Future()
        with self._lock:
            self._refs[ref] = out
        ref.future().add_done_callback(lambda f: self._settle(ref, f, out))
        return out

    def _settle(self, ref: Any, inner: Future, out: Future) -> None:
        from ray import exceptions as rex

        with self._lock:
            self._refs.pop(ref, None)
        try:
            out.set_result(inner.result())
        except rex.RayTaskError as err:
            cause = getattr(err, "cause", None)
            out.set_exception(cause if isinstance(cause, BaseException) else err)
        except (rex.WorkerCrashedError, rex.NodeDiedError, rex.ObjectLostError,
                rex.OwnerDiedError, rex.LocalRayletDiedError) as err:
            out.set_exception(WorkerLost(f"the Ray worker running the unit died: {err}"))
        except rex.TaskCancelledError as err:
            out.set_exception(BackendError(f"the unit was cancelled: {err}"))
        except BaseException as err:  # anything else reaches the runner through the future
            out.set_exception(err)

    def shutdown(self, cancel: bool = False) -> None:
        with self._lock:
            refs = list(self._refs)
        if cancel:
            for ref in refs:
                try:
                    self._ray.cancel(ref, force=True)
                except (ValueError, TypeError) as err:
                    log.debug("cancel %s: %s", ref, err)
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()


def make_backend(kind: str = "local", *, jobs: int | None = None, address: str | None = None,
                 cpus_per_unit: float | None = None, gpus_per_unit: float = 0.0,
                 runtime_env: dict[str, Any] | None = None) -> Backend:
    """The backend named ``kind`` ("local" or "ray")."""
    if kind == "local":
        return LocalBackend(2 if jobs is None else jobs)
    if kind == "ray":
        return RayBackend(address, cpus_per_unit=cpus_per_unit, gpus_per_unit=gpus_per_unit,
                          max_units=jobs, runtime_env=runtime_env)
    raise ConfigError(f"backend {kind!r}: use local or ray")
