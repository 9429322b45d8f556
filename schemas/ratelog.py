"""Logging that a flood cannot turn into a flood of log lines.

Refusals happen once per bad message, and a stranger can send thousands a second. Each kind
(a short tag such as ``unknown-robot``) logs its first ``burst`` occurrences in full; after
that at most one line per ``period_s``, saying how many were left out since the last one.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable


class RateLimitedLog:
    def __init__(self, logger: logging.Logger, burst: int = 5, period_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.logger = logger
        self.burst = burst
        self.period_s = period_s
        self.clock = clock
        self.seen: Counter[str] = Counter()
        self._held: Counter[str] = Counter()
        self._next_s: dict[str, float] = {}

    def log(self, level: int, kind: str, msg: str, *args: object, exc_info: bool = False
            ) -> bool:
        """Log ``msg % args`` under ``kind`` unless its quota is spent; True if it was."""
        self.seen[kind] += 1
        now = self.clock()
        if self.seen[kind] > self.burst and now < self._next_s.get(kind, 0.0):
            self._held[kind] += 1
            return False
        if self.seen[kind] >= self.burst:   # the burst's last line starts the first period
            self._next_s[kind] = now + self.period_s
        held = self._held.pop(kind, 0)
        if held:
            msg += f" (and {held} more {kind} since the last such line)"
        elif self.seen[kind] == self.burst:
            msg += f" (further {kind} lines at most every {self.period_s:g} s)"
        self.logger.log(level, msg, *args, exc_info=exc_info)
        return True

    def warning(self, kind: str, msg: str, *args: object) -> bool:
        return self.log(logging.WARNING, kind, msg, *args)

    def info(self, kind: str, msg: str, *args: object) -> bool:
        return self.log(logging.INFO, kind, msg, *args)
