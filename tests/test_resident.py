"""``server.offline.resident``: the read-only pages of mapped files given back, the process's
own pages kept, and what was released read back the same on use."""

from __future__ import annotations

import mmap
import sys
from pathlib import Path

import numpy as np
import pytest

from server.offline.resident import PageReleaser, releasable, release_file_pages

SMAPS = """\
00400000-00452000 r-xp 00000000 08:02 173521      /usr/lib/libfoo.so
Rss:                 200 kB
Anonymous:             0 kB
Locked:                0 kB
00652000-00653000 r--p 00052000 08:02 173521      /usr/lib/libfoo.so
Rss:                   4 kB
Anonymous:             4 kB
Locked:                0 kB
00653000-00654000 rw-p 00053000 08:02 173521      /usr/lib/libfoo.so
Rss:                   4 kB
Anonymous:             4 kB
00e03000-00e24000 rw-p 00000000 00:00 0           [heap]
Rss:                 132 kB
Anonymous:           132 kB
7f0000000000-7f0000100000 rw-p 00000000 00:00 0
Rss:                1024 kB
Anonymous:          1024 kB
7f1000000000-7f1000010000 r--p 00000000 08:02 42      /usr/lib/locked.so
Rss:                  64 kB
Anonymous:             0 kB
Locked:               64 kB
7f2000000000-7f2000010000 r--p 00000000 08:02 43      /usr/lib/cold.so
Rss:                   0 kB
Anonymous:             0 kB
7fff00000000-7fff00001000 r-xp 00000000 00:00 0   [vdso]
Rss:                   4 kB
Anonymous:             0 kB
7f3000000000-7f3000002000 r--s 00000000 08:02 44      /tmp/with space.bin
Rss:                   8 kB
Anonymous:             0 kB
"""


def test_only_read_only_file_pages_of_no_own_page_are_releasable() -> None:
    got = releasable(SMAPS)
    assert [(m.start, m.end, m.path, m.rss_kb) for m in got] == [
        (0x400000, 0x452000, "/usr/lib/libfoo.so", 200),
        (0x7F3000000000, 0x7F3000002000, "/tmp/with space.bin", 8),
    ]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/smaps: Linux")
def test_released_pages_leave_and_read_back_the_same(tmp_path: Path) -> None:
    data = np.arange(1 << 20, dtype=np.int64)          # 8 MB
    path = tmp_path / "mapped.bin"
    data.tofile(path)
    own = np.full(1 << 19, 7, dtype=np.int64)          # 4 MB of the process's own
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
        view = np.frombuffer(m, dtype=np.int64)
        assert int(view.sum()) == int(data.sum())      # every page touched

        def resident_kb() -> int:
            with open("/proc/self/smaps") as s:
                return sum(x.rss_kb for x in releasable(s.read()) if x.path == str(path))

        assert resident_kb() >= 7 * 1024
        released = release_file_pages()
        assert released >= 7 * 1024
        assert resident_kb() == 0
        assert int(view.sum()) == int(data.sum())      # mapped back from the file
        assert resident_kb() >= 7 * 1024
        del view
    assert int(own.sum()) == 7 * (1 << 19)             # the process's own pages untouched


def test_releaser_runs_at_most_once_per_period() -> None:
    now = [0.0]
    r = PageReleaser(every_s=5.0, clock=lambda: now[0])
    now[0] = 4.9
    assert r.maybe() == 0
    assert r._last == 0.0
    now[0] = 5.0
    r.maybe()
    assert r._last == 5.0
    now[0] = 9.0
    assert r.maybe() == 0
    assert r._last == 5.0


@pytest.mark.e2e
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/smaps: Linux")
def test_slam_log_process_releases_llvm_and_still_runs_the_kernels() -> None:
    """In a process readied as ``slam-log`` is (the kernels loaded), LLVM's pages are given
    back, and the compiled kernels and GTSAM still run and answer the same afterwards."""
    import subprocess

    code = (
        "import numpy as np\n"
        "import server.offline.slam_log\n"
        "from server.offline.resident import release_file_pages, releasable\n"
        "from server.slam.icp_kernel import build_grid\n"
        "def llvm_kb():\n"
        "    with open('/proc/self/smaps') as f:\n"
        "        return sum(m.rss_kb for m in releasable(f.read()) if 'llvmlite' in m.path)\n"
        "before = llvm_kb()\n"
        "assert before > 10_000, before\n"
        "assert release_file_pages() >= before\n"
        "assert llvm_kb() == 0\n"
        "x0, y0, nx, ny, start, order = build_grid(np.array([0.0, 1.0]), np.array([0.0, 1.0]),"
        " 0.5)\n"
        "assert (nx, ny) == (5, 5) and sorted(order) == [0, 1], (nx, ny, order)\n"
        "import gtsam\n"
        "p = gtsam.Pose2(1.0, 2.0, 0.5).compose(gtsam.Pose2(1.0, 0.0, 0.0))\n"
        "assert abs(p.x() - (1.0 + np.cos(0.5))) < 1e-12\n"
        "print('ok', before)\n")
    root = Path(__file__).resolve().parent.parent
    res = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True,
                         text=True, timeout=300, check=False)
    assert res.returncode == 0 and res.stdout.startswith("ok"), res.stderr[-2000:]


KERNEL = '''
from server.jit import njit_cached


@njit_cached
def twice(x):
    return 2.0 * x


twice(1.0)
'''


def test_kernels_cached_wants_a_fresh_index_per_kernel(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    from server.offline.lean_numba import kernels_cached

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    src = tmp_path / "kern.py"
    src.write_text("@njit_cached\ndef a(): pass\n@njit_cached\ndef b(): pass\n")
    (tmp_path / "plain.py").write_text("x = 1\n")
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    assert kernels_cached(tmp_path) is False                   # no cache at all
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    (cache / f"kern.a-1.{tag}.nbi").write_text("")
    assert kernels_cached(tmp_path) is False                   # one kernel of two
    (cache / f"kern.b-3.{tag}.nbi").write_text("")
    assert kernels_cached(tmp_path) is True
    t = src.stat().st_mtime + 10
    os.utime(src, (t, t))                                      # the source changed since
    assert kernels_cached(tmp_path) is False
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "elsewhere"))
    assert kernels_cached(tmp_path) is False


@pytest.mark.e2e
def test_kernels_compiled_apart_are_loaded_from_the_cache(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    """A module whose kernel is not cached is compiled in a child process; the import here
    then loads it from numba's cache (a hit, no compiling). numba reads ``NUMBA_CACHE_DIR``
    once, at its start: the child inherits this process's."""
    import importlib
    import os

    from server.offline.lean_numba import compile_apart, kernels_cached

    pkg = tmp_path / "apartpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "kern.py").write_text(KERNEL)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert kernels_cached(pkg) is False
    assert compile_apart("apartpkg.kern", pkg, timeout_s=300)
    assert kernels_cached(pkg) is True
    mod = importlib.import_module("apartpkg.kern")
    stats = mod.twice.stats
    assert sum(stats.cache_hits.values()) == 1 and not stats.cache_misses
    assert mod.twice(2.5) == 5.0
    # cached: no child at all (one importing this module would fail)
    assert compile_apart("apartpkg.nothing_to_import", pkg)
    # dated later, the same text (a branch switched and back): numba's index still holds, a
    # child loads it once, and the indexes are dated after the source again
    t = (pkg / "kern.py").stat().st_mtime - 10
    for index in (pkg / "__pycache__").glob("kern.*.nbi"):
        os.utime(index, (t, t))
    assert kernels_cached(pkg) is False
    assert compile_apart("apartpkg.kern", pkg, timeout_s=300)
    assert kernels_cached(pkg) is True
    (pkg / "kern.py").write_text(KERNEL + "\n")                 # changed: stale, a child runs
    assert not compile_apart("apartpkg.nothing_to_import", pkg)


@pytest.mark.e2e
def test_the_slam_kernels_compile_in_bare_children(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The children that fill an empty cache import only ``KERNEL_GROUPS``' modules of
    ``server.slam`` (no GTSAM, no back-end), and between them compile every kernel of it:
    afterwards the cache holds a fresh index for each, so ``slam-log`` compiles nothing."""
    from server.offline.lean_numba import KERNEL_GROUPS, SLAM, compile_apart, kernels_cached

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert kernels_cached(SLAM) is False
    assert compile_apart(groups=KERNEL_GROUPS, timeout_s=600)
    assert kernels_cached(SLAM) is True
