"""Freed memory goes back to the system on long runs (glibc's malloc_trim), at most so often."""

from __future__ import annotations

import ctypes.util
from pathlib import Path

import numpy as np
import pytest

from server.runtime import heap


def rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(ctypes.util.find_library("c") is None, reason="no C library to trim")
def test_trimming_returns_freed_small_blocks_to_the_system() -> None:
    # many small arrays (below the allocator's mmap threshold) freed in a pattern that leaves
    # the heap's top in use: the freed pages stay in the process until trimmed
    keep, drop = [], []
    for i in range(40000):
        (keep if i % 50 == 0 else drop).append(np.ones(256))     # 2 KB each, 80 MB in all
    del drop                                                     # 78 MB freed ...
    freed = rss_kb()
    assert heap.trim()
    assert freed - rss_kb() > 40_000                             # ... and given back
    assert len(keep) == 800 and all(k[0] == 1.0 for k in keep)  # what is in use stays


def test_the_trimmer_runs_at_most_once_per_period() -> None:
    t = [0.0]
    tr = heap.HeapTrimmer(every_s=30.0, clock=lambda: t[0])
    assert not tr.maybe()
    t[0] = 29.0
    assert not tr.maybe()
    t[0] = 30.5
    assert tr.maybe() == heap.trim() and tr.trims in (0, 1)
    t[0] = 31.0
    assert not tr.maybe()
