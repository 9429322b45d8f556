"""``slam-log``'s progress on a terminal: one line, ``slam-log  1234/29496 scans  0:42``,
rewritten at most every half second and cleared when done; nothing where the stream is not a
terminal. (It was a rich progress bar: rich's imports took 3.4 MB of a peak held to 250 MB.)"""

from __future__ import annotations

import sys
import time
from types import TracebackType
from typing import TextIO


class ScanCounter:
    def __init__(self, total: int, stream: TextIO | None = None, every_s: float = 0.5) -> None:
        self.total = total
        self.stream = sys.stderr if stream is None else stream
        self.every_s = every_s
        self.live = self.stream.isatty()
        self._t0 = self._last = time.monotonic()
        self._width = 0

    def update(self, done: int) -> None:
        now = time.monotonic()
        if not self.live or now - self._last < self.every_s:
            return
        self._last = now
        s = int(now - self._t0)
        line = f"slam-log  {done}/{self.total} scans  {s // 60}:{s % 60:02d}"
        self._width = max(self._width, len(line))
        self.stream.write("\r" + line.ljust(self._width))
        self.stream.flush()

    def __enter__(self) -> ScanCounter:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self.live and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
