"""glibc's threshold for serving an allocation by its own ``mmap``, fixed for ``slam-log``.

glibc serves a block of 128 KiB or more by its own mapping, given back to the system when
freed, but raises that threshold to the size of each such block freed (up to 32 MiB), so that
after a few loop-closure searches and likelihood fields a long run keeps their megabyte arrays
in its heap, where the blocks around them pin them when freed. Fixing the threshold keeps
every large array in its own mapping (``mallopt(M_MMAP_THRESHOLD)``; elsewhere than glibc,
nothing is done)."""

from __future__ import annotations

import ctypes
import ctypes.util

M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 128 << 10   # glibc's own starting value


def fixed_mmap_threshold(nbytes: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Fix glibc's mmap threshold at ``nbytes``; False where the C library has no ``mallopt``
    or refuses."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, nbytes))
