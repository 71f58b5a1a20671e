"""Folding repeated messages so a flood stays readable: once per window, with a count.

A link that is down makes MAVSDK log the same error once or twice a second, and an
autopilot in trouble repeats its warnings ("Low battery level!", a voltage that drops
by 0.01 V each time). :class:`RepeatFolder` lets a message through the first time and
then at most once per ``window_s``, saying how many repeats it folded in between.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable

_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")


def same_but_numbers(text: str) -> str:
    """``text`` with every number replaced by ``#``: "Battery 1 is low 10.49V" and
    "Battery 1 is low 10.48V" fold together."""
    return _NUMBER.sub("#", text)


class RepeatFolder:
    """Decides, per message, whether to show it now or fold it into a count.

    Args:
        window_s: how long identical messages are folded, seconds.
        clock: monotonic seconds (tests pass a fake one).
        key: what makes two messages "the same" (default: the text itself).
        max_keys: messages remembered at most (the oldest half is dropped beyond).
    """

    def __init__(
        self,
        window_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
        key: Callable[[str], str] = str,
        max_keys: int = 256,
    ) -> None:
        self.window_s, self.clock, self.key, self.max_keys = window_s, clock, key, max_keys
        self._lock = threading.Lock()
        # key -> [time it was last shown, repeats folded since]
        self._seen: dict[str, list[float]] = {}

    def admit(self, message: str) -> int | None:
        """None: a repeat inside the window (fold it); otherwise show it, and the number
        is how many repeats were folded since it was last shown (0: none)."""
        now = self.clock()
        k = self.key(message)
        with self._lock:
            seen = self._seen.get(k)
            if seen is not None and now - seen[0] < self.window_s:
                seen[1] += 1
                return None
            folded = int(seen[1]) if seen is not None else 0
            self._seen[k] = [now, 0]
            if len(self._seen) > self.max_keys:  # bounded: drop the oldest entries
                for old in sorted(self._seen, key=lambda x: self._seen[x][0])[: self.max_keys // 2]:
                    del self._seen[old]
        return folded

    def with_count(self, message: str, folded: int) -> str:
        """``message`` with "(and N more in W s)" when repeats were folded."""
        return f"{message} (and {folded} more in {self.window_s:.0f} s)" if folded else message
