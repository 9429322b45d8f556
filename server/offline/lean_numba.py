"""Imported first by ``server.offline.slam_log``, for its side effect: numba readies its CPU
target without SciPy's BLAS (``server.jit.skip_scipy_blas``: 14 MB resident that no kernel
uses) before anything loads the compiled kernels, which ``server.slam`` does at its import."""

from server.jit import skip_scipy_blas

skip_scipy_blas()
