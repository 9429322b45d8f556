"""numba without SciPy's BLAS, for a process whose compiled kernels use none (``slam-log``).

When numba first readies its CPU target, it checks whether a BLAS is there for ``np.dot`` and
``np.linalg`` in compiled code by importing ``scipy.linalg.cython_blas``. That maps SciPy's
own OpenBLAS and the ``scipy.linalg`` package into the process: 14 MB resident, which no
kernel of this project uses (ICP, normals and A* do no linear algebra in compiled code).
``skip_scipy_blas`` lets that check find no BLAS; SciPy's BLAS still imports as usual later,
for whoever asks for it.
"""

from __future__ import annotations

import sys

_BLAS = "scipy.linalg.cython_blas"


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
