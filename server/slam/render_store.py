"""What a keyframe keeps only to draw the map: its returns and the ends of its empty beams,
on disk by default.

The grid is drawn from these when a keyframe is added and again, from all keyframes, when an
optimisation moves them; matching never reads them. So they are written to a file (in single
precision, a micrometre at 100 m) instead of being held in memory. A render reads them back;
the operating system keeps a file it reads often in its cache, outside the process's own
memory.

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
F32 = NDArray[np.float32]

log = logging.getLogger(__name__)


def finite32(points: F64) -> F32:
    """Points (N, 2) in single precision, without non-finite rows."""
    p = np.asarray(points, dtype=np.float32).reshape(-1, 2)
    return p[np.isfinite(p).all(axis=1)]


class RenderStore:
    """An append-only, unlinked file of float32 (N, 2) arrays, read back by offset
    (thread-safe)."""

    def __init__(self, folder: str | None = None) -> None:
        fd, path = tempfile.mkstemp(prefix="mrslam-render-", dir=folder)
        os.unlink(path)
        self._fd = fd
        self._end = 0
        self._lock = threading.Lock()

    def put(self, q: F32) -> int:
        raw = np.ascontiguousarray(q, dtype=np.float32).tobytes()
        with self._lock:
            at = self._end
            self._end += len(raw)
        written = os.pwrite(self._fd, raw, at)
        if written != len(raw):
            raise OSError(f"render store: wrote {written} of {len(raw)} bytes")
        return at

    def get(self, at: int, rows: int) -> F32:
        n = rows * 2 * 4
        raw = os.pread(self._fd, n, at)
        if len(raw) != n:
            raise OSError(f"render store: read {len(raw)} of {n} bytes at {at}")
        return np.frombuffer(raw, dtype=np.float32).reshape(rows, 2)

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
    the robot frame, in single precision, on disk (or in memory where no file can be made)."""

    __slots__ = ("_at", "_q", "_store", "n_hits", "n_misses")

    def __init__(self, q: F32, n_hits: int, spill: bool = True) -> None:
        self.n_hits = int(n_hits)
        self.n_misses = len(q) - self.n_hits
        self._store = store() if spill and len(q) else None
        self._at = -1
        self._q: F32 | None = None
        if self._store is not None:
            try:
                self._at = self._store.put(q)
            except OSError as e:
                log.warning("keyframe map data kept in memory: %s", e)
                self._store = None
        if self._store is None:
            kept = np.array(q, dtype=np.float32)
            kept.flags.writeable = False
            self._q = kept

    @classmethod
    def of(cls, hits: F64, misses: F64, spill: bool = True) -> RenderScan:
        h = finite32(hits)
        return cls(np.concatenate([h, finite32(misses)]), len(h), spill)

    @property
    def on_disk(self) -> bool:
        return self._store is not None

    @property
    def nbytes(self) -> int:
        """Bytes held in memory for the points (0 when they are on disk)."""
        return 0 if self._q is None else self._q.nbytes

    def stored(self) -> F32:
        """Hits then misses (N + K, 2), single precision, read-only."""
        if self._q is not None:
            return self._q
        assert self._store is not None
        q = self._store.get(self._at, self.n_hits + self.n_misses)
        q.flags.writeable = False
        return q

    def points(self) -> tuple[F32, F32]:
        """``(hits, misses)`` in metres, single precision, read-only."""
        p = self.stored()
        return p[:self.n_hits], p[self.n_hits:]

    @property
    def hits(self) -> F32:
        return self.points()[0]

    @property
    def misses(self) -> F32:
        return self.points()[1]

    def __reduce__(self) -> tuple[object, tuple[F32, int]]:
        return (RenderScan, (self.stored(), self.n_hits))
