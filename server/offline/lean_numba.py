"""Imported first by ``server.offline.slam_log``, for its side effects on the start's peak.

numba readies its CPU target without SciPy's BLAS (``server.jit.skip_scipy_blas``: 14 MB
resident that no kernel uses) before anything loads the compiled kernels, which
``server.slam`` does at its import. The start is then taken in steps, and after each the
pages of the libraries' files that it ran are given back (``server.offline.resident``), so
that they do not add up: readying the target (about 40 MB of LLVM's library), numba's typing
tables (what loading the first kernel would do first: 50 MB more of LLVM), and GTSAM's import
(its module registers thousands of classes: about 25 MB of its library). What is run again
later is mapped back on use. On ``slam-log``'s start this takes the peak from 171 MB to about
112 MB.

Where numba's cache does not hold ``server.slam``'s kernels yet (a first run, or a kernel's
source changed since), they are compiled in a child process first (``compile_apart``), which
writes the cache this process then loads them from: compiling here would keep about 60 MB
more for the whole run (numba keeps what it compiled, the heap the rest) and take the start
to about 215 MB (243 MB at the peak of a short log). The child's own peak is about 218 MB.
"""

from __future__ import annotations

import importlib
import logging
import os
import subprocess
import sys
import time
import types
from collections.abc import Sequence
from pathlib import Path

from server.jit import skip_scipy_blas
from server.offline.resident import release_file_pages

log = logging.getLogger(__name__)

SLAM = Path(__file__).resolve().parent.parent / "slam"
_CHILD = "MRSLAM_COMPILING_KERNELS"
# the modules of ``server.slam`` whose import compiles its kernels (a warm-up at the end of
# each), in the children that compile them: the matcher's apart, since compiling it alone
# raises a child's peak by about 80 MB
KERNEL_GROUPS: tuple[tuple[str, ...], ...] = (("icp",), ("scan", "grid", "loop_kernel"))


def _cache_dirs(folder: Path) -> list[Path] | None:
    """Where numba keeps the cache of ``folder``'s modules: ``NUMBA_CACHE_DIR`` if set, else
    the folder's ``__pycache__``; None where that cannot be written (numba then looks in the
    user's cache folder, which is not looked into here)."""
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given:
        return [Path(given)]
    tree = folder / "__pycache__"
    return [tree] if os.access(tree if tree.is_dir() else folder, os.W_OK) else None


def kernels_cached(folder: Path = SLAM) -> bool | None:
    """Whether numba's cache holds, for every module of ``folder`` with compiled kernels
    (``@njit_cached``), an index for each of them written since the module's source last
    changed; None where the cache is not where it is looked for (``_cache_dirs``)."""
    tag = f".py{sys.version_info.major}{sys.version_info.minor}.nbi"
    where = _cache_dirs(folder)
    if where is None:
        return None
    dirs = [d for d in where if d.is_dir()]
    for src in sorted(folder.glob("*.py")):
        kernels = src.read_text(encoding="utf-8").count("@njit_cached")
        if not kernels:
            continue
        stamp = src.stat().st_mtime
        fresh = sum(1 for d in dirs for f in d.rglob(f"{src.stem}.*{tag}")
                    if f.stat().st_mtime >= stamp)
        if fresh < kernels:
            return False
    return True


def import_bare(package: str, folder: Path, modules: Sequence[str]) -> None:
    """Import ``modules`` of ``package`` (found in ``folder``) without running the package's
    ``__init__``, which would import all the rest (for ``server.slam``: GTSAM and the
    back-end, about 90 MB that compiling the kernels does not need)."""
    if package not in sys.modules:
        pkg = types.ModuleType(package)
        pkg.__path__ = [str(folder)]
        sys.modules[package] = pkg
    for m in modules:
        importlib.import_module(f"{package}.{m}")


def compile_apart(module: str = "server.slam", folder: Path = SLAM,
                  timeout_s: float = 900.0,
                  groups: Sequence[Sequence[str]] | None = None) -> bool:
    """Compile the kernels of ``module`` (those of ``folder``) into numba's cache in child
    processes, their start taken in steps as here. With ``groups``, one child per group
    imports only those modules of the package (``import_bare``), whose imports compile their
    kernels; without, one child imports ``module`` whole. Nothing is done in such a child
    itself, where the cache holds the kernels already, or where it is not looked for. False
    if a child failed: this process then compiles the rest at the import, as before
    (logged)."""
    if os.environ.get(_CHILD) or kernels_cached(folder) is not False:
        return True
    t0 = time.perf_counter()
    env = {**os.environ, _CHILD: "1",
           "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    codes = ([f"import server.offline.lean_numba as L; L.import_bare({module!r}, "
              f"L.Path({str(folder)!r}), {list(g)!r})" for g in groups] if groups
             else [f"import server.offline.lean_numba, {module}"])
    for code in codes:
        if not _run_child(code, env, timeout_s):
            return False
    log.info("SLAM kernels compiled into numba's cache in %.1f s", time.perf_counter() - t0)
    _mark_fresh(folder)
    return True


def _run_child(code: str, env: dict[str, str], timeout_s: float) -> bool:
    try:
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, timeout=timeout_s, check=False)
    except (OSError, subprocess.SubprocessError) as e:
        log.warning("compiling the SLAM kernels apart failed (%s): compiled here instead", e)
        return False
    if res.returncode != 0:
        log.warning("compiling the SLAM kernels apart failed (exit %d: %s): compiled here "
                    "instead", res.returncode, res.stderr.strip()[-300:])
        return False
    return True


def _mark_fresh(folder: Path) -> None:
    """Date the cache's indexes of ``folder``'s modules now, after a child has loaded or
    compiled every kernel. numba judges an index by its module's content, ``kernels_cached``
    by dates: a source whose date changed but not its text (a branch switched and back, a
    file touched) keeps numba's index as it was, and without this every later start would
    run the child again."""
    tag = f".py{sys.version_info.major}{sys.version_info.minor}.nbi"
    for d in _cache_dirs(folder) or []:
        if not d.is_dir():
            continue
        for src in folder.glob("*.py"):
            for f in d.rglob(f"{src.stem}.*{tag}"):
                try:
                    os.utime(f)
                except OSError as e:   # the next start runs the child again: only slower
                    log.info("could not date %s (%s)", f, e)


if skip_scipy_blas():
    release_file_pages()
    from numba.core.registry import cpu_target

    cpu_target.typing_context.refresh()   # done by the first kernel's load otherwise
    release_file_pages()
    if not os.environ.get(_CHILD):     # a child that compiles imports no back-end
        import gtsam  # noqa: F401  (imported by server.slam's back-end)

        release_file_pages()
        compile_apart(groups=KERNEL_GROUPS)
