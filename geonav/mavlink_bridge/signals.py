"""SIGINT, SIGTERM and SIGHUP end a flight like Ctrl-C: LAND/RTL, wait for disarm, record.

:func:`stop_signals` installs the handlers (main thread only) for the length of a
flight; the first signal raises :class:`FlightInterrupted` in the flight loop, later
ones are logged, and none interrupts the landing itself.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

log = logging.getLogger(__name__)


class FlightInterrupted(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP during a flight (handled like Ctrl-C: land, record)."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(signal.Signals(signum).name)


class StopSignals:
    """Turns the first SIGINT/SIGTERM/SIGHUP into :class:`FlightInterrupted`; later ones are logged.

    Installed only in the main thread; a SIGINT that is ignored (a background
    job) stays ignored, SIGTERM and SIGHUP still land the vehicle.
    """

    SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")

    def __init__(self) -> None:
        self.received: int | None = None
        self.may_raise = True
        self._old: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for name in self.SIGNALS:
            sig = getattr(signal, name, None)
            if sig is None:
                continue
            old = signal.getsignal(sig)
            if sig == signal.SIGINT and old is signal.SIG_IGN:
                continue
            self._old[sig] = old
            signal.signal(sig, self._handle)

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.received is None:
            self.received = signum
            log.error("%s received: ending the flight (LAND/RTL as configured)", name)
            if self.may_raise:
                raise FlightInterrupted(signum)
            return
        log.warning("%s received again: geonav is already ending the flight", name)


@contextmanager
def stop_signals() -> Iterator[StopSignals]:
    """SIGINT/SIGTERM/SIGHUP end the flight like Ctrl-C while the block runs."""
    sigs = StopSignals()
    sigs.install()
    try:
        yield sigs
    finally:
        sigs.restore()
