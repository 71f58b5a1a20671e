"""The unit folder of an experiment run: the unit records, result.json, the lock.

A unit is one stage of an experiment for one seed (:class:`Unit`); it trains in its
folder ``RUN/units/<stage>/seed-<s>/`` (:func:`unit_dir`), which holds
``progress.json`` while it trains, ``result.json`` when done (:func:`write_result`,
:func:`read_result`: paths relative to the run folder), ``error.txt`` when it raised,
``retries.json`` when its worker died, and ``.lock`` (:func:`unit_lock`) while a
process trains it; :func:`run_unit` and :func:`run_group` (what the backends execute)
train units in their folders under these rules. The runner
(:mod:`geonav.experiments.runner`) and the report (:mod:`geonav.experiments.report`)
both read these records from here.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geonav.errors import GeonavError

# The lock's warnings keep the logger name they had in the runner (users filter on it).
log = logging.getLogger("geonav.experiments.runner")

RESULT = "result.json"
PROGRESS = "progress.json"
LOCK = ".lock"
ERROR = "error.txt"
RETRIES = "retries.json"


class UnitLocked(GeonavError):
    """A unit folder is being trained by another live process."""


@dataclass(frozen=True)
class Unit:
    """One stage for one seed."""

    stage: str
    seed: int

    @property
    def key(self) -> str:
        return f"{self.stage}/seed-{self.seed}"


@dataclass
class UnitEvent:
    """Progress of the experiment, for the CLI's bars."""

    unit: Unit | None
    status: str  # "skipped" | "started" | "progress" | "done" | "retry" | "failed"
    episodes: int = 0
    budget: int = 0
    done_units: int = 0
    total_units: int = 0
    message: str = ""
    run: str = ""  # the experiment's name (a sweep runs several)


def unit_dir(root: Path, unit: Unit) -> Path:
    return root / "units" / unit.stage / f"seed-{unit.seed}"


def read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


RESULT_PATHS = ("checkpoint", "metrics", "evals", "scene", "tasks")
"""The keys of a unit's ``result.json`` that hold paths."""

SHARED_INPUTS = "inputs"
"""A sweep's folder of shared scenes and task sets, beside its run folders."""


def run_root(unit_folder: Path) -> Path:
    """The run folder of a unit folder ``RUN/units/<stage>/seed-<s>`` (lexically: a unit
    folder that links to another run's unit is still this run's)."""
    return Path(os.path.abspath(unit_folder)).parents[2]


def write_result(out: Path, result: dict[str, Any]) -> None:
    """Write a unit's ``result.json`` with its paths relative to the run folder, so a run
    folder that is copied or moved is read from where it is. A path outside the run folder
    (a scene or task set the config names, other than a sweep's shared ``inputs/`` beside
    it) stays absolute."""
    root = run_root(out)
    stored = dict(result)
    for key in RESULT_PATHS:
        value = stored.get(key)
        if not value:
            continue
        path = os.path.abspath(value)
        for base in (root, root.parent / SHARED_INPUTS):
            rel = os.path.relpath(path, base)
            if not rel.startswith(".."):
                stored[key] = os.path.relpath(path, root)
                break
    write_json(out / RESULT, stored)


def read_result(out: Path) -> dict[str, Any] | None:
    """A unit's ``result.json`` (None when absent or unreadable) with its paths absolute.

    Relative ones are taken from the run folder. Absolute ones (result.json files written
    before paths were relative) that lie in the folder the run was in when it ran (found
    from the unit's own ``units/<stage>/seed-<s>`` segment) are moved to where the run
    folder is now."""
    result = read_json(out / RESULT)
    if result is None:
        return None
    root = run_root(out)
    old_root = _old_root(result, Path(os.path.abspath(out)))
    for key in RESULT_PATHS:
        value = result.get(key)
        if not value:
            continue
        if not os.path.isabs(value):
            result[key] = os.path.normpath(root / value)
            continue
        if old_root is None or old_root == root:
            continue
        for old, new in ((old_root, root),
                         (old_root.parent / SHARED_INPUTS, root.parent / SHARED_INPUTS)):
            rel = os.path.relpath(value, old)
            if not rel.startswith(".."):
                result[key] = str(new / rel)
                break
    return result


def _old_root(result: dict[str, Any], out: Path) -> Path | None:
    """The run folder an old result.json's absolute paths were written in: the prefix
    before this unit's ``units/<stage>/seed-<s>`` in any of them."""
    segment = f"{os.sep}units{os.sep}{out.parent.name}{os.sep}{out.name}{os.sep}"
    for key in RESULT_PATHS:
        value = result.get(key)
        if isinstance(value, str) and os.path.isabs(value) and segment in value:
            return Path(value[:value.index(segment)])
    return None


LOCK_WAIT_S = 5.0
"""How long a unit waits for its folder's lock (a killed holder takes a moment to exit)."""


@contextmanager
def unit_lock(out: Path, wait_s: float = LOCK_WAIT_S) -> Iterator[None]:
    """Hold the unit folder ``out`` exclusively while a unit trains in it.

    An ``flock`` on ``out/.lock``: the kernel drops it when the holder exits in any way,
    so a killed holder never blocks a rerun; the file names the holder (pid, host) while
    it runs and is emptied on a clean release, so a non-empty file found on acquiring
    is the stale record of a holder that was killed, and is logged as such.

    Args:
        out: the unit folder.
        wait_s: keep trying this long before giving up (a holder that was just killed
            releases the lock only once all its threads have exited).

    Raises:
        UnitLocked: another live process (this or another machine of a shared folder)
            is training this unit.
    """
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError as err:
                if time.monotonic() < deadline:
                    time.sleep(0.1)
                    continue
                holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or \
                    "another process"
                raise UnitLocked(f"unit folder {out} is in use by {holder}: another run of this "
                                 "experiment is training it; wait for it to finish or stop "
                                 "it first") from err
        try:
            stale = os.pread(fd, 4096, 0).decode(errors="replace").strip()
            if stale:
                log.warning("unit folder %s: the previous holder %s is gone (%s); taking over "
                            "its stale lock", out, stale, _holder_state(stale))
            me = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                             "since": round(time.time(), 3)})
            os.ftruncate(fd, 0)
            os.pwrite(fd, me.encode(), 0)
            yield
        finally:
            os.ftruncate(fd, 0)  # released cleanly: nothing stale left behind
    finally:
        os.close(fd)  # closing the descriptor releases the flock


def read_lock(out: Path) -> dict[str, Any] | None:
    """The holder recorded in a unit folder's lock file (None when free or unreadable)."""
    return read_json(out / LOCK)


def _holder_state(text: str) -> str:
    try:
        holder = json.loads(text)
        pid, host = int(holder["pid"]), str(holder["host"])
    except (ValueError, KeyError, TypeError):
        return "unreadable record"
    if host != socket.gethostname():
        return f"on host {host}"
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return f"pid {pid} is not running"
    except PermissionError:
        pass
    return f"pid {pid} exists but no longer holds the lock"


def run_unit(payload: dict[str, Any]) -> dict[str, Any]:
    """Run one unit in this process (the function backends execute).

    Holds the unit folder's lock, writes ``result.json`` when done, and on an exception
    writes its traceback to ``error.txt`` in the unit folder before re-raising.
    """
    from geonav.experiments.stages import execute_stage

    out = Path(payload["out_dir"])
    with unit_lock(out):
        (out / ERROR).unlink(missing_ok=True)
        t0 = time.time()
        try:
            result = execute_stage(payload)
        except Exception:
            (out / ERROR).write_text(traceback.format_exc())
            raise
        result["wall_s_this_session"] = time.time() - t0
        result["worker"] = {"host": socket.gethostname(), "pid": os.getpid()}
        write_result(out, result)
    return result


def run_group(payloads: list[dict[str, Any]]) -> dict[str, Any]:
    """Run a packed group (several units of one stage, see :func:`packs`) in this process.

    Holds every member's lock, writes each member's ``result.json`` (and on an exception
    the traceback to each member's ``error.txt``); returns ``{"members": [results]}``.
    """
    from contextlib import ExitStack

    from geonav.experiments.stages import execute_group

    outs = [Path(p["out_dir"]) for p in payloads]
    with ExitStack() as stack:
        for out in outs:
            stack.enter_context(unit_lock(out))
            (out / ERROR).unlink(missing_ok=True)
        t0 = time.time()
        try:
            results = execute_group(payloads)
        except Exception:
            for out in outs:
                (out / ERROR).write_text(traceback.format_exc())
            raise
        for out, result in zip(outs, results, strict=True):
            result["wall_s_this_session"] = time.time() - t0
            result["worker"] = {"host": socket.gethostname(), "pid": os.getpid(),
                                "packed_with": len(outs)}
            write_result(out, result)
    return {"members": results}
