"""Giving freed memory back to the operating system on a long run.

Scan matching makes and drops many arrays of a few kilobytes each. The C allocator keeps what is
freed for later use, and over hours the process's resident memory holds a growing share of
freed but unreturned pages (on the real logs, about a quarter of what SLAM added). glibc's
``malloc_trim`` returns them. ``HeapTrimmer.maybe()`` calls it at most once per ``every_s`` of
wall time (a few milliseconds each); elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import time
from collections.abc import Callable


def _malloc_trim() -> Callable[[int], int] | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


_TRIM = _malloc_trim()


def trim() -> bool:
    """Return freed heap memory to the system now; False where the C library cannot."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


class HeapTrimmer:
    """``trim()`` at most once per ``every_s`` seconds of wall time."""

    def __init__(self, every_s: float = 30.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s = every_s
        self._clock = clock
        self._last = clock()
        self.trims = 0

    def maybe(self) -> bool:
        now = self._clock()
        if now - self._last < self.every_s:
            return False
        self._last = now
        if trim():
            self.trims += 1
            return True
        return False


_process_trimmer = HeapTrimmer()


def maybe_trim() -> bool:
    """The process's own ``HeapTrimmer``: for a loop that runs for hours (the server's core)."""
    return _process_trimmer.maybe()
