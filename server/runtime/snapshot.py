"""Snapshots of the server's core, so a restart need not replay the journal from the start.

A snapshot is the whole core pickled (each pose graph as its factors, in their slots, and its
linearisation point: ``PoseGraph.__getstate__``; caches and search trees left out and rebuilt)
with the journal sequence number it was taken at, compressed. Arrays that never change once
made (marked read-only: keyframe scans, submaps) are not in the snapshot but in the folder's
append-only ``blobs.bin``, each written once and referred to by its digest, so a snapshot holds
only what changes and costs little however long the run.

Taken by a forked copy of the server (``server.runtime.snapfork``: ``begin`` forks, the child
pickles and writes, ``finish`` puts it in place), or pickled in process (``prepare`` and
``commit``) where there is no ``fork``; both give the same bytes.

A server that resumes loads the newest snapshot that reads back and replays only the journal
after it; a snapshot that is missing, cut short or from another version of mrslam is
passed over for the one before (the last ``keep`` are kept), and without any the journal is
replayed whole. A snapshot is read back only by the code that wrote it (the header holds the
version and a digest of the server's code): an upgraded server replays the journal instead.
Written atomically (beside, fsync, rename). The state folder is the server's own: unpickling
runs code, so it must not be writable by others.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import io
import logging
import os
import pickle
import re
import struct
import time
import weakref
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from server.runtime.hugepages import Collapser
from server.runtime.snapfork import Forked, fork

#: the memory is gathered into huge pages after a snapshot whose fork held the worker this
#: long (gathering costs the writer about 1 ms of CPU per MB; below this it is not worth it)
COLLAPSE_ABOVE_HOLD_S = 0.004

if TYPE_CHECKING:
    from server.core import ServerCore

log = logging.getLogger(__name__)

MAGIC = b"MRSLAMSNAP2\n"
BLOB_MAGIC = b"MB"
BLOB_MIN_BYTES = 2048          # smaller read-only arrays stay in the snapshot
_BLOB_HEAD = struct.Struct("<2s16sI")   # magic, digest, length of the compressed bytes


def _version() -> str:
    """mrslam's version and a digest of the code whose objects a snapshot holds: a snapshot
    is read back only by the very code that wrote it (another one replays the journal)."""
    try:
        version = importlib.metadata.version("mrslam")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    h = hashlib.blake2b(digest_size=8)
    root = Path(__file__).resolve().parents[2]
    for package in ("server", "factors", "schemas"):
        for f in sorted((root / package).rglob("*.py")):
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
    return f"{version}+{h.hexdigest()}"


VERSION = _version()
_NAME = re.compile(r"snapshot-(\d{12})\.pkl$")


class BlobStore:
    """Append-only store of immutable arrays, keyed by the digest of their bytes.

    Each record: ``MB``, a 16-byte BLAKE2b digest, the length, then the zlib-compressed array
    bytes. Opening reads the index and cuts a torn tail (a crash mid-append), so what a
    snapshot refers to was synced before the snapshot itself was renamed into place.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.index: dict[bytes, tuple[int, int]] = {}
        self._known: dict[int, tuple[weakref.ref[np.ndarray], bytes]] = {}   # id -> digest
        self.appended_bytes = 0
        self._data: bytes | None = None    # the file, while a snapshot is being read
        end = 0
        if path.exists():
            data = path.read_bytes()
            while end + _BLOB_HEAD.size <= len(data):
                magic, digest, n = _BLOB_HEAD.unpack_from(data, end)
                start = end + _BLOB_HEAD.size
                if magic != BLOB_MAGIC or start + n > len(data):
                    break
                self.index[digest] = (start, n)
                end = start + n
            if end < len(data):
                log.warning("%s: %d byte(s) of torn tail cut", path.name, len(data) - end)
                with path.open("r+b") as f:
                    f.truncate(end)
        self._file = path.open("ab")

    def digest(self, a: np.ndarray) -> bytes:
        """The digest of ``a``, appended to the store if it is not there yet."""
        known = self._known.get(id(a))
        if known is not None and known[0]() is a:
            return known[1]
        raw = np.ascontiguousarray(a).tobytes()
        d = hashlib.blake2b(raw, digest_size=16).digest()
        if d not in self.index:
            packed = zlib.compress(raw, 1)
            self._file.write(_BLOB_HEAD.pack(BLOB_MAGIC, d, len(packed)))
            self.index[d] = (self._file.tell(), len(packed))
            self._file.write(packed)
            self.appended_bytes += _BLOB_HEAD.size + len(packed)
        self.remember(a, d)
        return d

    def remember(self, a: np.ndarray, digest: bytes) -> None:
        """Know ``a`` by its digest without hashing it again (while it lives)."""
        key = id(a)
        self._known[key] = (weakref.ref(a, lambda _r: self._known.pop(key, None)), digest)

    def flush(self) -> None:
        self._file.flush()

    def sync(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())

    def read(self, digest: bytes) -> bytes:
        start, n = self.index[digest]
        if self._data is None or start + n > len(self._data):
            self._file.flush()
            self._data = self.path.read_bytes()
        return zlib.decompress(self._data[start:start + n])

    def done_reading(self) -> None:
        self._data = None

    def close(self) -> None:
        self._file.close()


class _Pickler(pickle.Pickler):
    def __init__(self, f: io.BytesIO, blobs: BlobStore) -> None:
        super().__init__(f, protocol=pickle.HIGHEST_PROTOCOL)
        self.blobs = blobs

    def persistent_id(self, obj: Any) -> Any:
        if (type(obj) is np.ndarray and not obj.flags.writeable and obj.nbytes >= BLOB_MIN_BYTES
                and not obj.dtype.hasobject):
            return ("nd", self.blobs.digest(obj), obj.dtype.str, obj.shape)
        return None


class _Unpickler(pickle.Unpickler):
    def __init__(self, f: io.BytesIO, blobs: BlobStore) -> None:
        super().__init__(f)
        self.blobs = blobs

    def persistent_load(self, pid: Any) -> Any:
        kind, digest, dtype, shape = pid
        if kind != "nd":
            raise pickle.UnpicklingError(f"unknown reference {kind!r}")
        try:
            raw = self.blobs.read(digest)
        except KeyError:
            raise pickle.UnpicklingError("an array it refers to is not in blobs.bin") from None
        a = np.frombuffer(raw, dtype=np.dtype(dtype)).reshape(shape)   # read-only, as it was
        self.blobs.remember(a, digest)
        return a


@dataclass(frozen=True)
class Pending:
    """A snapshot pickled and not yet written: its sequence, the pickle, the bytes its new
    arrays added to the blob store, and the time pickling took."""

    sequence: int
    pickled: bytes
    blob_bytes: int
    seconds: float


class Snapshots:
    """Writes and finds the snapshots of one state folder."""

    def __init__(self, state_dir: str | Path, keep: int = 2) -> None:
        self.dir = Path(state_dir)
        self.keep = keep
        self.last_seconds = 0.0
        self.last_cpu_s = 0.0     # the last forked snapshot's process's CPU
        self.last_bytes = 0
        self._blobs: BlobStore | None = None
        self.use_fork = True      # ``begin`` forks (copy-on-write) where it can
        #: after each child, the writer may gather the server's memory into huge pages again,
        #: so that the next fork copies fewer page tables (``server.runtime.hugepages``; a
        #: ``Collapser`` here). Not by default: while the kernel gathers, the worker's page
        #: faults wait for the process's memory map, and at 50 robots a scan then took 40–190
        #: ms of wall time for 5–7 ms of CPU, every robot's answers late for a second after
        #: each snapshot; the fork it saves is a few ms (``docs/state-and-recovery.md``)
        self.huge_pages: Collapser | None = None

    @property
    def blobs(self) -> BlobStore:
        if self._blobs is None:
            self._blobs = BlobStore(self.dir / "blobs.bin")
        return self._blobs

    def write(self, core: ServerCore, sequence: int) -> Path:
        """Snapshot ``core`` as of journal entry ``sequence`` (the next one to come)."""
        return self.commit(self.prepare(core, sequence))

    def prepare(self, core: ServerCore, sequence: int) -> Pending:
        """The part that must see the core still: pickled (new arrays to the blob store).
        ``commit`` does the rest, and may do it on another thread while the core goes on."""
        t0 = time.monotonic()
        buf = io.BytesIO()
        before = self.blobs.appended_bytes
        _Pickler(buf, self.blobs).dump(core)
        self.blobs.flush()       # whole records in the file (synced to disk by ``commit``)
        return Pending(sequence, buf.getvalue(), self.blobs.appended_bytes - before,
                       time.monotonic() - t0)

    def commit(self, pending: Pending) -> Path:
        """Compress and write a prepared snapshot atomically; drop the oldest."""
        t0 = time.monotonic()
        self.blobs.sync()        # every array the snapshot refers to is on disk before it is
        tmp, path, size = self.write_beside(pending)
        self._install(tmp, path)
        self.last_seconds = pending.seconds + time.monotonic() - t0
        self.last_bytes = size + pending.blob_bytes
        return path

    def write_beside(self, pending: Pending) -> tuple[Path, Path, int]:
        """The snapshot compressed into a file beside its place, synced; its size."""
        body = zlib.compress(pending.pickled, 1)
        head = (MAGIC + struct.pack("<Q", pending.sequence)
                + VERSION.encode()[:64].ljust(64, b" "))
        path = self.dir / f"snapshot-{pending.sequence:012d}.pkl"
        tmp = path.with_name(f".{path.name}.tmp")
        try:
            with tmp.open("wb") as f:
                f.write(head)
                f.write(struct.pack("<Q", len(body)))
                f.write(body)
                f.flush()
                os.fsync(f.fileno())
        except OSError:
            tmp.unlink(missing_ok=True)    # a full disk: leave no half snapshot behind
            raise
        return tmp, path, len(body)

    def _install(self, tmp: Path, path: Path) -> None:
        try:
            os.replace(tmp, path)
        except OSError:
            tmp.unlink(missing_ok=True)
            raise
        for old in self.paths()[self.keep:]:
            old.unlink(missing_ok=True)

    # -- copy-on-write: a child process pickles and writes, the worker only forks --------------
    def begin(self, core: ServerCore, sequence: int) -> Pending | Forked:
        """Start a snapshot of ``core`` as of ``sequence``: a forked child process (a frozen
        copy of the server, memory shared until written) pickles and writes it, and the
        caller goes on at once; ``finish`` collects it. Where there is no ``fork`` (or it
        fails), pickled here (``prepare``) instead."""
        if self.use_fork and hasattr(os, "fork"):
            try:
                return fork(self, core, sequence)
            except OSError as e:
                log.warning("snapshot: fork failed (%s): pickled in the server's thread", e)
        return self.prepare(core, sequence)

    def finish(self, job: Pending | Forked) -> Path:
        """Write what ``begin`` started (the writer thread): a forked child's snapshot is
        waited for and put in its place; its new arrays join the blob store's index."""
        if isinstance(job, Pending):
            return self.commit(job)
        try:
            report = job.collect()
        finally:
            # no child lives now: every page is ours alone. A small server forks fast anyway
            if self.huge_pages is not None and job.hold_s >= COLLAPSE_ABOVE_HOLD_S:
                self.huge_pages.collapse()
        blobs = self.blobs
        for digest, start, n in report["blobs"]:
            blobs.index[digest] = (start, n)
        blobs.appended_bytes += report["blob_bytes"]
        tmp, path = Path(report["tmp"]), Path(report["path"])
        self._install(tmp, path)
        self.last_seconds = report["seconds"]
        self.last_cpu_s = report["cpu_s"]
        self.last_bytes = report["size"] + report["blob_bytes"]
        return path

    def reset(self) -> None:
        """After a failed write: the blob store is opened afresh, which reads back what is
        really in it (cutting a torn tail), so no later snapshot refers to an array that
        never reached the disk."""
        blobs, self._blobs = self._blobs, None
        if blobs is not None:
            # its buffer may not be written either: what is on the disk is read back anew
            with contextlib.suppress(OSError):
                blobs.close()

    def paths(self) -> list[Path]:
        """The snapshots, newest first."""
        found = [p for p in self.dir.glob("snapshot-*.pkl") if _NAME.search(p.name)]
        return sorted(found, key=lambda p: p.name, reverse=True)

    def load(self) -> tuple[ServerCore, int] | None:
        """The newest snapshot that reads back whole: the core and its sequence number."""
        for path in self.paths():
            try:
                return _read(path, self.blobs)
            except (OSError, ValueError, EOFError, pickle.UnpicklingError, AttributeError,
                    ImportError, TypeError, RuntimeError, zlib.error) as e:
                log.warning("snapshot %s passed over: %s", path.name, e)
        return None


def _read(path: Path, blobs: BlobStore) -> tuple[ServerCore, int]:
    data = path.read_bytes()
    n = len(MAGIC)
    if data[:n] != MAGIC:
        raise ValueError("not a snapshot")
    (sequence,) = struct.unpack("<Q", data[n:n + 8])
    version = data[n + 8:n + 72].decode(errors="replace").strip()
    if version != VERSION:
        raise ValueError(f"written by mrslam {version}, this is {VERSION}")
    (size,) = struct.unpack("<Q", data[n + 72:n + 80])
    body = data[n + 80:]
    if len(body) != size:
        raise ValueError(f"cut short ({len(body)} of {size} bytes)")
    try:
        core = _Unpickler(io.BytesIO(zlib.decompress(body)), blobs).load()
    finally:
        blobs.done_reading()
    return core, int(sequence)
