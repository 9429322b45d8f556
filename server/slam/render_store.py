"""What a keyframe keeps only to draw the map: its returns and the ends of its empty beams,
compact and, by default, on disk.

The grid is drawn from these when a keyframe is added and again, from all keyframes, when an
optimisation moves them; matching never reads them. So they are kept as 16-bit integers in the
robot frame (a step of 1 mm, or coarser for a scan reaching past 32 m: a step of range/32767,
at most 2.5 mm for an 80 m laser, a twentieth of a grid cell) and written to a file instead of
being held in memory. A render reads them back; the operating system keeps a file it reads
often in its cache, outside the process's own memory.

The file (``RenderStore``) is created in ``MRSLAM_RENDER_DIR``, or the server's state folder, or
the system's temporary folder, and unlinked at once: it lives while the process has it open and
never outlives the process, however it ends. A process that cannot create it anywhere (a
read-only or full disk) keeps the arrays in memory and says so once. A keyframe pickled
(snapshots, other processes) carries its arrays, not a place in the file.
"""

from __future__ import annotations

import logging
import os
import tempfile
import threading

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I16 = NDArray[np.int16]

log = logging.getLogger(__name__)

STEP_M = 1e-3        # the finest step; coarser for scans reaching past 32.767 m
_QMAX = 32767


def quantise(hits: F64, misses: F64) -> tuple[I16, float]:
    """Both point sets (N, 2) and (K, 2) stacked as int16 steps, and the step [m]."""
    both = np.concatenate([np.asarray(hits, dtype=np.float64).reshape(-1, 2),
                           np.asarray(misses, dtype=np.float64).reshape(-1, 2)])
    finite = np.isfinite(both).all(axis=1)
    both = both[finite]
    reach = float(np.abs(both).max()) if len(both) else 0.0
    step = max(STEP_M, reach / _QMAX)
    q = np.clip(np.rint(both / step), -_QMAX, _QMAX).astype(np.int16)
    return q, step


class RenderStore:
    """An append-only, unlinked file of int16 arrays, read back by offset (thread-safe)."""

    def __init__(self, folder: str | None = None) -> None:
        fd, path = tempfile.mkstemp(prefix="mrslam-render-", dir=folder)
        os.unlink(path)
        self._fd = fd
        self._end = 0
        self._lock = threading.Lock()
        self.bytes = 0

    def put(self, q: I16) -> int:
        raw = np.ascontiguousarray(q, dtype=np.int16).tobytes()
        with self._lock:
            at = self._end
            self._end += len(raw)
        written = os.pwrite(self._fd, raw, at)
        if written != len(raw):
            raise OSError(f"render store: wrote {written} of {len(raw)} bytes")
        self.bytes += len(raw)
        return at

    def get(self, at: int, rows: int) -> I16:
        n = rows * 2 * 2
        raw = os.pread(self._fd, n, at)
        if len(raw) != n:
            raise OSError(f"render store: read {len(raw)} of {n} bytes at {at}")
        return np.frombuffer(raw, dtype=np.int16).reshape(rows, 2)

    def close(self) -> None:
        os.close(self._fd)


_store: RenderStore | None = None
_store_failed = False
_store_lock = threading.Lock()
_store_pid = 0
_folder: str | None = None


def use_folder(folder: str | os.PathLike[str]) -> None:
    """Make the store in ``folder`` unless ``MRSLAM_RENDER_DIR`` says otherwise (the server
    uses its state folder); no effect once the store is made."""
    global _folder
    _folder = os.fspath(folder)


def store() -> RenderStore | None:
    """The process's store, created on first use; None where no file can be made (the arrays
    then stay in memory). A forked child makes its own, so parent and child never write at the
    same offsets of one file."""
    global _store, _store_failed, _store_pid
    if _store_failed:
        return None
    with _store_lock:
        if _store is None or _store_pid != os.getpid():
            folder = os.environ.get("MRSLAM_RENDER_DIR") or _folder
            tried = []
            for where in dict.fromkeys([folder, None]):      # then the temporary folder
                try:
                    _store = RenderStore(where)
                    _store_pid = os.getpid()
                    break
                except OSError as e:
                    tried.append(f"{where or tempfile.gettempdir()}: {e}")
            else:
                _store_failed = True
                log.warning("keyframes' map data stay in memory: no file for them (%s)",
                            "; ".join(tried))
                return None
            if tried:
                log.warning("keyframes' map data go to %s: %s", tempfile.gettempdir(), tried[0])
        return _store


class RenderScan:
    """A keyframe's returns (``hits``) and the ends of its beams without one (``misses``), in
    the robot frame, as int16 steps on disk (or in memory where no file can be made)."""

    __slots__ = ("_at", "_q", "_store", "n_hits", "n_misses", "step_m")

    def __init__(self, q: I16, step_m: float, n_hits: int, spill: bool = True) -> None:
        self.step_m = float(step_m)
        self.n_hits = int(n_hits)
        self.n_misses = len(q) - self.n_hits
        self._store = store() if spill and len(q) else None
        self._at = -1
        self._q: I16 | None = None
        if self._store is not None:
            try:
                self._at = self._store.put(q)
            except OSError as e:
                log.warning("keyframe map data kept in memory: %s", e)
                self._store = None
        if self._store is None:
            kept = np.array(q, dtype=np.int16)
            kept.flags.writeable = False
            self._q = kept

    @classmethod
    def of(cls, hits: F64, misses: F64, spill: bool = True) -> RenderScan:
        q, step = quantise(hits, misses)
        n_hits = int(np.isfinite(np.asarray(hits, dtype=np.float64).reshape(-1, 2)).all(axis=1)
                     .sum())
        return cls(q, step, n_hits, spill)

    @property
    def on_disk(self) -> bool:
        return self._store is not None

    @property
    def nbytes(self) -> int:
        """Bytes held in memory for the points (0 when they are on disk)."""
        return 0 if self._q is None else self._q.nbytes

    def quantised(self) -> I16:
        """The int16 steps, hits then misses (N + K, 2), read-only."""
        if self._q is not None:
            return self._q
        assert self._store is not None
        q = self._store.get(self._at, self.n_hits + self.n_misses)
        q.flags.writeable = False
        return q

    def points(self) -> tuple[F64, F64]:
        """``(hits, misses)`` in metres, float64."""
        p = self.quantised().astype(np.float64) * self.step_m
        return p[:self.n_hits], p[self.n_hits:]

    @property
    def hits(self) -> F64:
        return self.points()[0]

    @property
    def misses(self) -> F64:
        return self.points()[1]

    def __reduce__(self) -> tuple[object, tuple[I16, float, int]]:
        return (RenderScan, (self.quantised(), self.step_m, self.n_hits))
