"""Snapshots of the server's core, so a restart need not replay the journal from the start.

A snapshot is the whole core pickled (each pose graph as its factors, in their slots, and its
linearisation point: ``PoseGraph.__getstate__``) with the journal sequence number it was taken
at. A server that resumes loads the newest snapshot that reads back and replays only the
journal after it; a snapshot that is missing, cut short or from another version of mrslam is
passed over for the one before (the last ``keep`` are kept), and without any the journal is
replayed whole. Written atomically (beside, fsync, rename). The state folder is the server's
own: unpickling runs code, so it must not be writable by others.
"""

from __future__ import annotations

import importlib.metadata
import logging
import os
import pickle
import re
import struct
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.core import ServerCore

log = logging.getLogger(__name__)

MAGIC = b"MRSLAMSNAP1\n"


def _version() -> str:
    try:
        return importlib.metadata.version("mrslam")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


VERSION = _version()
_NAME = re.compile(r"snapshot-(\d{12})\.pkl$")


class Snapshots:
    """Writes and finds the snapshots of one state folder."""

    def __init__(self, state_dir: str | Path, keep: int = 2) -> None:
        self.dir = Path(state_dir)
        self.keep = keep
        self.last_seconds = 0.0
        self.last_bytes = 0

    def write(self, core: ServerCore, sequence: int) -> Path:
        """Snapshot ``core`` as of journal entry ``sequence`` (the next one to come)."""
        t0 = time.monotonic()
        body = pickle.dumps(core, protocol=pickle.HIGHEST_PROTOCOL)
        head = MAGIC + struct.pack("<Q", sequence) + VERSION.encode()[:64].ljust(64, b" ")
        path = self.dir / f"snapshot-{sequence:012d}.pkl"
        tmp = path.with_name(f".{path.name}.tmp")
        with tmp.open("wb") as f:
            f.write(head)
            f.write(struct.pack("<Q", len(body)))
            f.write(body)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        for old in self.paths()[self.keep:]:
            old.unlink(missing_ok=True)
        self.last_seconds, self.last_bytes = time.monotonic() - t0, len(body)
        return path

    def paths(self) -> list[Path]:
        """The snapshots, newest first."""
        found = [p for p in self.dir.glob("snapshot-*.pkl") if _NAME.search(p.name)]
        return sorted(found, key=lambda p: p.name, reverse=True)

    def load(self) -> tuple[ServerCore, int] | None:
        """The newest snapshot that reads back whole: the core and its sequence number."""
        for path in self.paths():
            try:
                return _read(path)
            except (OSError, ValueError, EOFError, pickle.UnpicklingError, AttributeError,
                    ImportError, TypeError, RuntimeError) as e:
                log.warning("snapshot %s passed over: %s", path.name, e)
        return None


def _read(path: Path) -> tuple[ServerCore, int]:
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
    core = pickle.loads(body)
    return core, int(sequence)
