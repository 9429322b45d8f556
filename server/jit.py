"""Setting up numba for the compiled kernels (ICP, normals, A*, the map analysis).

``njit_cached``: compile once and keep the machine code in numba's cache, so that later
processes load it instead of compiling (compiling costs seconds and about 50 MB more at the
peak). numba writes its cache beside the source (``__pycache__``), else in the user's cache
folder (``NUMBA_CACHE_DIR``, or ``~/.cache``); where it can write neither (an install in a
read-only place, with no writable home), it refuses the decorator. The kernels then compile
in each process instead, and the first such kernel logs that once.

``skip_scipy_blas``: numba without SciPy's BLAS, for a process whose compiled kernels use
none (``slam-log``).

When numba first readies its CPU target, it checks whether a BLAS is there for ``np.dot`` and
``np.linalg`` in compiled code by importing ``scipy.linalg.cython_blas``. That maps SciPy's
own OpenBLAS and the ``scipy.linalg`` package into the process: 14 MB resident, which no
kernel of this project uses (ICP, normals and A* do no linear algebra in compiled code).
``skip_scipy_blas`` lets that check find no BLAS; SciPy's BLAS still imports as usual later,
for whoever asks for it.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from typing import Any, TypeVar, cast

from numba import njit

log = logging.getLogger(__name__)

_BLAS = "scipy.linalg.cython_blas"
Fn = TypeVar("Fn", bound=Callable[..., Any])
_uncached: list[str] = []


def njit_cached(fn: Fn) -> Fn:
    """``njit(cache=True, nogil=True)``, or without the cache where numba has nowhere to
    write it (logged once per process)."""
    try:
        return cast("Fn", njit(cache=True, nogil=True)(fn))
    except RuntimeError as e:
        if "no locator available" not in str(e):
            raise
    if not _uncached:
        log.warning("numba can write its cache nowhere (%s's folder, NUMBA_CACHE_DIR, the "
                    "user's cache folder): the compiled kernels are compiled in this process",
                    fn.__module__)
    _uncached.append(f"{fn.__module__}.{fn.__qualname__}")
    return cast("Fn", njit(nogil=True)(fn))


def skip_scipy_blas() -> bool:
    """Ready numba's CPU target without loading SciPy's BLAS (compiled code then cannot use
    ``np.dot``/``np.linalg``: numba says so if a kernel tries). False, and nothing done, if
    numba has readied it already or SciPy's BLAS is loaded anyway."""
    if "numba.np.arraymath" in sys.modules or _BLAS in sys.modules:
        return False
    sys.modules[_BLAS] = None  # type: ignore[assignment]  # an import of it fails, once
    try:
        import numba.np.arraymath  # noqa: F401  (its import checks for a BLAS, once)
    finally:
        if _BLAS in sys.modules and sys.modules[_BLAS] is None:
            del sys.modules[_BLAS]
    return True
