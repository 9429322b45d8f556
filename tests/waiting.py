"""Waiting in tests for something another thread or process does."""

from __future__ import annotations

import time
from collections.abc import Callable


def within(cond: Callable[[], bool], timeout_s: float) -> bool:
    """Whether ``cond()`` becomes true within ``timeout_s`` (polled every 10 ms)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if cond():
            return True
        time.sleep(0.01)
    return cond()
