"""A snapshot taken by a forked child process: copy-on-write, so the worker only forks.

Pickling the whole core takes the worker hundreds of milliseconds late in a mission
(``bench/snapshot_cost.py``). ``fork`` gives a child that is a frozen copy of the server at that
instant (its memory shared with the parent until either writes a page), so the snapshot is
consistent with the journal's position by construction, whatever the core holds. The child
pickles the core (new immutable arrays appended to ``blobs.bin``), compresses and writes the
snapshot beside its place, syncs both, reports over a pipe and exits; the parent's writer
thread waits for the report, syncs the journal and renames the snapshot into place (so the
journal before a snapshot is on disk first, as ever).

The child runs no other thread of the server's and touches nothing but the state folder: it
collects no garbage (no finaliser of the parent's runs in it), takes the default action on
the stop signals, and leaves with ``os._exit`` whatever happens. While it lives, the parent's
garbage collector passes over the objects made before the fork (``gc.freeze``), so that it does
not write into every page and copy them all. One child at a time: the
keeper starts the next snapshot only when the writer has finished the last.
"""

from __future__ import annotations

import gc
import os
import pickle
import select
import signal
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NoReturn

if TYPE_CHECKING:
    from server.core import ServerCore
    from server.runtime.snapshot import Snapshots


#: a child that has not reported by then is ended, and the snapshot counted as failed
CHILD_TIMEOUT_S = 300.0


class SnapshotProcessError(OSError):
    """The child that took a snapshot failed (its error, e.g. a full disk), or died."""


@dataclass(frozen=True)
class Forked:
    """A snapshot a child process is taking: its sequence, the child, the read end of its
    pipe, and how long forking held the caller."""

    sequence: int
    pid: int
    fd: int
    hold_s: float

    def collect(self) -> dict[str, Any]:
        """Wait for the child's report (the writer thread). Raises ``SnapshotProcessError``
        when it failed or died."""
        chunks = []
        late = False
        deadline = time.monotonic() + CHILD_TIMEOUT_S
        try:
            while True:
                ready, _, _ = select.select([self.fd], [], [],
                                            max(0.0, deadline - time.monotonic()))
                if not ready:        # hung (a lock another thread held at the fork?): ended
                    late = True
                    os.kill(self.pid, signal.SIGKILL)
                    break
                if not (chunk := os.read(self.fd, 1 << 16)):
                    break
                chunks.append(chunk)
        finally:
            os.close(self.fd)
            _, status = os.waitpid(self.pid, 0)
            gc.unfreeze()        # the parent's collector sees every object again
        if late:
            raise SnapshotProcessError(0, f"snapshot {self.sequence}: its process did not "
                                          f"finish within {CHILD_TIMEOUT_S:.0f} s and was ended")
        code = os.waitstatus_to_exitcode(status)
        try:
            report: dict[str, Any] = pickle.loads(b"".join(chunks))
        except Exception:
            report = {"error": f"its process ended with {code} and no report"}
        if "error" in report or code != 0:
            raise SnapshotProcessError(report.get("errno") or 0,
                                       f"snapshot {self.sequence}: {report.get('error', code)}")
        return report


def fork(snaps: Snapshots, core: ServerCore, sequence: int) -> Forked:
    """Fork a child that snapshots ``core`` as of ``sequence`` (see the module)."""
    t0 = time.perf_counter()
    snaps.blobs.flush()      # nothing of the parent's left in a buffer for the child to write
    r, w = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        os.close(r)
        os.close(w)
        raise
    if pid == 0:
        _child(snaps, core, sequence, r, w)
    os.close(w)
    gc.freeze()   # while the child lives, the parent's collector leaves its pages shared
    return Forked(sequence, pid, r, time.perf_counter() - t0)


def _child(snaps: Snapshots, core: ServerCore, sequence: int, r: int, w: int) -> NoReturn:
    code = 1
    try:
        gc.disable()
        os.nice(10)   # background work: the worker's answers come first on a busy machine
        _die_with_parent()
        os.close(r)
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
        t0 = time.monotonic()
        blobs = snaps.blobs
        known = set(blobs.index)
        try:
            pending = snaps.prepare(core, sequence)
            blobs.sync()        # the arrays it refers to are on disk before the snapshot is
            tmp, path, size = snaps.write_beside(pending)
            report: dict[str, Any] = {
                "blobs": [(d, *blobs.index[d]) for d in blobs.index if d not in known],
                "blob_bytes": pending.blob_bytes, "tmp": str(tmp), "path": str(path),
                "size": size, "pickle_s": pending.seconds,
                "seconds": time.monotonic() - t0, "cpu_s": time.process_time()}
            code = 0
        except BaseException as e:
            report = {"error": f"{type(e).__name__}: {e}", "errno": getattr(e, "errno", None)}
        view = memoryview(pickle.dumps(report))
        while view:
            view = view[os.write(w, view):]
    finally:
        os._exit(code)


def _die_with_parent() -> None:
    """(Linux) The child is killed when the server dies, SIGKILL included, so no snapshot
    process outlives it. Linux sends the signal when the *thread* that forked the child
    ends: the worker waits for its snapshot before it stops (``ServerNode._work``)."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)        # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
