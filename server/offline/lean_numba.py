"""Imported first by ``server.offline.slam_log``, for its side effects on the start's peak.

numba readies its CPU target without SciPy's BLAS (``server.jit.skip_scipy_blas``: 14 MB
resident that no kernel uses) before anything loads the compiled kernels, which
``server.slam`` does at its import. The start is then taken in steps, and after each the
pages of the libraries' files that it ran are given back (``server.offline.resident``), so
that they do not add up: readying the target (about 40 MB of LLVM's library), numba's typing
tables (what loading the first kernel would do first: 50 MB more of LLVM), and GTSAM's import
(its module registers thousands of classes: about 25 MB of its library). What is run again
later is mapped back on use. On ``slam-log``'s start this takes the peak from 171 MB to about
130 MB."""

from server.jit import skip_scipy_blas
from server.offline.resident import release_file_pages

if skip_scipy_blas():
    release_file_pages()
    from numba.core.registry import cpu_target

    cpu_target.typing_context.refresh()   # done by the first kernel's load otherwise
    release_file_pages()
    import gtsam  # noqa: F401  (imported by server.slam's back-end)

    release_file_pages()
