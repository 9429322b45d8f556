"""Imported first by ``server.offline.slam_log``, for its side effect: numba readies its CPU
target without SciPy's BLAS (``server.jit.skip_scipy_blas``: 14 MB resident that no kernel
uses) before anything loads the compiled kernels, which ``server.slam`` does at its import.
The pages of LLVM's library that readying the target ran (about 40 MB) are then given back
(``server.offline.resident``), so that they and the kernels' loading do not add up at the
start's peak."""

from server.jit import skip_scipy_blas
from server.offline.resident import release_file_pages

if skip_scipy_blas():
    release_file_pages()
