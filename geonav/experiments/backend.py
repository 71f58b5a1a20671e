"""Where units of work run: the scheduling seam of the experiment runner.

A unit (one stage for one seed, or any other independent piece of work) is a
picklable call ``fn(*args) -> dict``. The runner only needs :class:`Backend`:
``submit`` returns a :class:`concurrent.futures.Future`, ``shutdown`` stops.
:class:`LocalBackend` runs units in local worker processes. A distributed
backend (e.g. Ray: ``ray.remote(fn).remote(*args)`` wrapped into a Future
with ``ObjectRef.future()``) only has to implement the same two methods;
nothing in the experiment logic changes.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from typing import Any, Protocol


class Backend(Protocol):
    """Runs independent units of work."""

    slots: int
    """How many units may run at once."""

    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any) -> Future:
        """Start ``fn(*args)``; the future's result is the unit's result dict."""

    def shutdown(self, cancel: bool = False) -> None:
        """Release the workers; ``cancel`` drops queued units."""


class LocalBackend:
    """Units in up to ``jobs`` local processes (spawned: each gets a clean torch state).

    Args:
        jobs: concurrent units; 0 runs units inline in threads of this process (tests).
    """

    def __init__(self, jobs: int = 1) -> None:
        self.slots = max(1, jobs)
        if jobs <= 0:
            self._pool: ProcessPoolExecutor | ThreadPoolExecutor = ThreadPoolExecutor(1)
        else:
            self._pool = ProcessPoolExecutor(max_workers=jobs,
                                             mp_context=mp.get_context("spawn"))

    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any) -> Future:
        return self._pool.submit(fn, *args)

    def shutdown(self, cancel: bool = False) -> None:
        self._pool.shutdown(wait=not cancel, cancel_futures=cancel)
