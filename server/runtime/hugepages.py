"""Gather the server's anonymous memory into huge pages, so that forking for a snapshot is cheap.

``fork`` copies the page tables of every private page the process has written, and the
worker thread is held while it does (``server.runtime.snapfork``): about 4 ms per 100 MB of
4 KB pages here. A 2 MB huge page is one entry instead of 512, so the same memory in huge
pages forks in a fraction of that time (``bench/snapshot_cost.py``). The kernel does not
give the server huge pages by itself (its default is to give them only to memory that asks),
and the pages a snapshot child shares with the server are split back into small ones as the
server writes to them. So, once each child has exited, the writer thread asks the kernel to
gather the process's anonymous regions into huge pages again (``MADV_COLLAPSE``, Linux 6.1
and later). The kernel copies each 2 MB range on its own, holding the process's memory map
only while it swaps a range in; the worker goes on meanwhile.

Where the kernel cannot (an older kernel, no transparent huge pages, another system) nothing
happens, and the reason is kept once in ``Collapser.unavailable``.
"""

from __future__ import annotations

import ctypes
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

HUGE = 1 << 21
MADV_COLLAPSE = 25
THP_SETTING = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def anonymous_ranges(maps_text: str) -> list[tuple[int, int]]:
    """The 2 MB-aligned parts of the private, writable, anonymous regions (and the heap) in a
    ``/proc/<pid>/maps`` text, as ``(start, length)``; regions smaller than 2 MB are left."""
    out = []
    for line in maps_text.splitlines():
        fields = line.split()
        if len(fields) < 5 or not fields[1].startswith("rw") or fields[1][3] != "p":
            continue
        name = fields[5] if len(fields) > 5 else ""
        if name not in ("", "[heap]"):
            continue
        lo, hi = (int(x, 16) for x in fields[0].split("-"))
        lo = (lo + HUGE - 1) & ~(HUGE - 1)
        hi &= ~(HUGE - 1)
        if hi - lo >= HUGE:
            out.append((lo, hi - lo))
    return out


def kernel_version(release: str) -> tuple[int, int]:
    """``(major, minor)`` of a kernel release string; ``(0, 0)`` when it cannot be read."""
    m = re.match(r"(\d+)\.(\d+)", release)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


@dataclass
class Collapser:
    """Asks the kernel to gather this process's anonymous memory into huge pages."""

    unavailable: str | None = None
    runs: int = 0
    seconds: float = 0.0
    last_seconds: float = 0.0
    refused: int = 0      # ranges the kernel left as they were (busy, short of memory)
    _madvise: object = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not sys.platform.startswith("linux"):
            self.unavailable = f"not on Linux ({sys.platform})"
            return
        release = os.uname().release
        if kernel_version(release) < (6, 1):
            self.unavailable = f"Linux {release} cannot collapse pages (6.1 and later can)"
            return
        try:
            if "[never]" in THP_SETTING.read_text():
                self.unavailable = "transparent huge pages are off ([never])"
                return
            libc = ctypes.CDLL(None, use_errno=True)
            madvise = libc.madvise
        except (OSError, AttributeError) as e:
            self.unavailable = f"no transparent huge pages or madvise here ({e})"
            return
        madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        madvise.restype = ctypes.c_int
        self._madvise = madvise

    def collapse(self) -> float:
        """Gather what can be gathered (the writer thread, while no snapshot child lives);
        returns the seconds it took (0 when unavailable)."""
        if self.unavailable is not None or self._madvise is None:
            return 0.0
        t0 = time.perf_counter()
        try:
            ranges = anonymous_ranges(Path("/proc/self/maps").read_text())
        except OSError as e:
            self.unavailable = f"/proc/self/maps cannot be read ({e})"
            return 0.0
        madvise = self._madvise
        for start, length in ranges:
            if madvise(start, length, MADV_COLLAPSE) != 0:   # type: ignore[operator]
                self.refused += 1      # EAGAIN/ENOMEM/EINVAL on a part: left as it is
        self.runs += 1
        self.last_seconds = time.perf_counter() - t0
        self.seconds += self.last_seconds
        return self.last_seconds
