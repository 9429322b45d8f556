"""Giving back the pages of the libraries' files that ``slam-log`` mapped and no longer runs.

A process's resident memory counts every page of a mapped file it has touched, and it keeps
them until the system is short of memory. ``slam-log`` touches most of its read-only library
pages once: LLVM (``libllvmlite.so``) readies numba's target and loads the compiled kernels
from numba's cache at import, about 65 MB of its code and constants, and never runs again
unless a kernel has to be compiled; GTSAM's module registers thousands of classes at import
(about 20 MB) and the run then calls a small part of it. ``release_file_pages`` unmaps those
pages from the process (``madvise(MADV_DONTNEED)`` on its read-only mappings of files): they
stay in the system's file cache, and a page the process runs again is mapped back from there
on its first use (a minor fault, well under a microsecond). The run's own memory (its heap and
every anonymous or written page) is never touched: a mapping is released only if it cannot be
written and holds no page of its own (``Anonymous: 0`` in ``/proc/self/smaps``), so nothing
is lost by dropping it.

Linux only; elsewhere (no ``/proc/self/smaps`` or no ``madvise``) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)

MADV_DONTNEED = 4
SMAPS = "/proc/self/smaps"


@dataclass(frozen=True, slots=True)
class FileMapping:
    """A read-only mapping of a file with resident pages and none of its own."""

    start: int
    end: int
    path: str
    rss_kb: int


def _madvise() -> Callable[[int, int, int], int] | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.madvise
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    fn.restype = ctypes.c_int
    return fn


_MADVISE = _madvise()


def releasable(smaps_text: str) -> list[FileMapping]:
    """The mappings of ``smaps_text`` (``/proc/<pid>/smaps``) that may be released: a file's
    (not ``[heap]``, ``[stack]``, ``[vdso]``... nor anonymous), not writable, with resident
    pages and no anonymous (written, copied) page."""
    out: list[FileMapping] = []
    head: tuple[int, int, str] | None = None
    rss = anon = 0
    locked = False

    def close() -> None:
        if head is not None and rss > 0 and anon == 0 and not locked:
            out.append(FileMapping(head[0], head[1], head[2], rss))

    for line in smaps_text.splitlines():
        first, _, rest = line.partition(" ")
        if "-" in first and not first.endswith(":"):
            close()
            head = None
            rss = anon = 0
            locked = False
            fields = rest.split(None, 4)
            if len(fields) < 5:      # an anonymous mapping
                continue
            perms, path = fields[0], fields[4].strip()
            if perms[1] != "-" or not path.startswith("/"):
                continue
            lo, hi = first.split("-")
            head = (int(lo, 16), int(hi, 16), path)
        elif head is not None:
            value = rest.split()
            if first == "Rss:":
                rss = int(value[0])
            elif first == "Anonymous:":
                anon = int(value[0])
            elif first == "Locked:":
                locked = int(value[0]) > 0
    close()
    return out


def release_file_pages() -> int:
    """Unmap the resident pages of the process's read-only file mappings (see the module);
    returns the kB released (0 where this cannot be done)."""
    if _MADVISE is None:
        return 0
    try:
        with open(SMAPS) as f:
            text = f.read()
    except OSError:
        return 0
    released = 0
    for m in releasable(text):
        if _MADVISE(m.start, m.end - m.start, MADV_DONTNEED) == 0:
            released += m.rss_kb
    return released


class PageReleaser:
    """``release_file_pages()`` at most once per ``every_s`` seconds of wall time, so that
    the process keeps mapped only what it ran since (the working set, mapped back on use)."""

    def __init__(self, every_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s = every_s
        self._clock = clock
        self._last = clock()
        self.released_kb = 0

    def maybe(self) -> int:
        now = self._clock()
        if now - self._last < self.every_s:
            return 0
        self._last = now
        kb = release_file_pages()
        self.released_kb += kb
        return kb
