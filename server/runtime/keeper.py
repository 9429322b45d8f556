"""The server's state on disk, kept through a full disk: the journal and the snapshots.

Writing the state must never stop the robots. So every write of the journal and of a
snapshot goes through here, and a write that fails (a full disk, a folder gone read-only, an
I/O error):

1. is logged once, with the error, and counted (``failures``, by what failed);
2. suspends journaling: the robots keep being served, and what the server processes from then
   on is not journaled (counted: ``not_journaled``). The journal and snapshot written before
   stay: a server killed now resumes as it was when writing stopped;
3. every ``retry_s``, once the folder has room for a snapshot again, the server takes a fresh
   snapshot of everything it holds and starts a new journal segment after it: journaling
   resumes (``resumed``), and a restart from then on loses nothing.

A snapshot that fails while the journal still writes only counts and is tried again at the
next period: the journal alone still holds everything.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from server.runtime.journal import JournalWriter
from server.runtime.snapshot import Snapshots
from server.runtime.writer import BackgroundWriter

if TYPE_CHECKING:
    from schemas import Scan, TagDetections
    from server.command.operator import OperatorCommand
    from server.core import ServerCore

log = logging.getLogger(__name__)

#: room a fresh snapshot needs beyond the last one's size before journaling is tried again
SPARE_BYTES = 1 << 20


class StateKeeper:
    def __init__(self, journal: JournalWriter, retry_s: float = 5.0) -> None:
        self.journal: JournalWriter | None = journal
        self.dir = journal.dir
        self.snapshots = Snapshots(journal.dir)
        self.retry_s = retry_s
        self.sequence = journal.sequence      # the next entry's, also while suspended
        self.bytes = 0                        # journaled, over every segment of this run
        self.seconds = 0.0
        self.failures: Counter[str] = Counter()
        self.not_journaled = 0
        self.resumed = 0
        self.last_error = ""
        self.snapshot_s: list[float] = []     # how long each took to pickle and write
        self.snapshot_hold_s: list[float] = []   # how long each held the worker (a fork)
        self.snapshot_bytes = 0               # written in all: snapshots and new blobs
        self._lock = threading.Lock()         # failures come from the writer thread too
        self._broken: str | None = None       # a failure the worker has not acted on yet
        self._next_try = 0.0
        self._outage = False     # a failure was logged; the next is not, until writing works
        self._cpu_mark = (time.process_time(), time.monotonic())

    # -- entries (the worker thread) ---------------------------------------------------------
    def scan(self, msg: Scan, now_ns: int | None) -> None:
        self._entry(lambda j: j.scan(msg, now_ns))

    def tags(self, msg: TagDetections) -> None:
        self._entry(lambda j: j.tags(msg))

    def alive(self, robot_id: str, alive: bool, stamp_ns: int) -> None:
        self._entry(lambda j: j.alive(robot_id, alive, stamp_ns))

    def operator(self, cmd: OperatorCommand, stamp_ns: int) -> None:
        self._entry(lambda j: j.operator(cmd, stamp_ns))

    def gave(self, robot_ids: list[str], stamp_ns: int) -> None:
        self._entry(lambda j: j.gave(robot_ids, stamp_ns))

    def adopted(self, parcel: bytes, stamp_ns: int) -> None:
        self._entry(lambda j: j.adopted(parcel, stamp_ns))

    @property
    def writing(self) -> bool:
        return self.journal is not None

    def _entry(self, write: Callable[[JournalWriter], None]) -> None:
        j = self.journal
        if j is None:
            self.not_journaled += 1
            return
        try:
            write(j)
        except OSError as e:
            self.failed("journal", e)
            self._suspend()
            self.not_journaled += 1
            return
        self.sequence = j.sequence

    # -- the worker's periodic work ----------------------------------------------------------
    def flush_due(self, now: float) -> bool:
        return self.journal is not None and now >= self.journal.next_flush

    def flush(self, writer: BackgroundWriter) -> None:
        """The chunk in progress to the operating system here, to the disk on the writer."""
        j = self.journal
        if j is None:
            return
        try:
            j.flush(sync=False)
        except OSError as e:
            self.failed("journal", e)
            self._suspend()
            return
        writer.submit("journal", j.sync)

    def snapshot(self, core: ServerCore, writer: BackgroundWriter, wait: bool = True) -> bool:
        """Snapshot ``core`` as of the journal's next entry: a forked copy of the server
        pickles and writes it (``Snapshots.begin``), and it is put in place here (``wait``)
        or by the writer thread. False: it could not be written (``wait``), or an earlier one
        is still being written."""
        if not wait and writer.busy("snapshot"):
            return False       # the last one is still being written: the next round takes it
        if self.journal is not None:
            try:
                self.journal.flush(sync=False)   # the journal holds everything before it ...
            except OSError as e:
                self.failed("journal", e)
                self._suspend()
        if self.journal is None and not wait:
            return False       # suspended: only a snapshot that resumes journaling is taken
        journal, snapshots = self.journal, self.snapshots
        if wait:
            writer.drain()       # one snapshot at a time (a child appends to the blob store)
        t0 = time.perf_counter()
        try:
            job = snapshots.begin(core, self.sequence)
        except OSError as e:
            self._snapshot_failure(e)
            return False
        self.snapshot_hold_s.append(time.perf_counter() - t0)

        def commit() -> None:
            if journal is not None:
                journal.sync()           # ... on the disk before the snapshot is
            snapshots.finish(job)
            if self.journal is not None:
                with self._lock:
                    self._outage = False     # everything is written again
            self.snapshot_s.append(snapshots.last_seconds)
            self.snapshot_bytes += snapshots.last_bytes

        if not wait:
            writer.submit("snapshot", commit)
            return True
        try:
            commit()
        except OSError as e:
            self._snapshot_failure(e)
            return False
        return True

    def snapshot_interval_s(self, now: float, period_s: float) -> float:
        """``period_s``, or longer so that snapshots take at most ~4 % of the CPU the server
        uses (however large the state grows, however busy the server is)."""
        cpu = time.process_time()
        last_cpu, last_wall = self._cpu_mark
        self._cpu_mark = (cpu, now)
        used = (cpu - last_cpu) / max(now - last_wall, 1e-3)   # cores the server uses
        return max(period_s, self.snapshots.last_seconds / (0.04 * max(used, 0.05)))

    def maintain(self, core: ServerCore, writer: BackgroundWriter) -> None:
        """(the worker, every round) Act on a failure the writer thread saw; while suspended,
        once there is room again, snapshot and journal anew."""
        with self._lock:
            broken, self._broken = self._broken, None
        if broken == "journal":
            self._suspend()
        if self.journal is not None or time.monotonic() < self._next_try:
            return
        self._next_try = time.monotonic() + self.retry_s
        need = self.snapshots.last_bytes + SPARE_BYTES
        try:
            if shutil.disk_usage(self.dir).free < need:
                return
        except OSError:
            return
        if not self.snapshot(core, writer, wait=True):
            return
        try:
            self.journal = JournalWriter(self.dir, first_sequence=self.sequence)
        except Exception as e:
            self.failed("journal", e)
            return
        self.resumed += 1
        with self._lock:
            self._outage = False
        log.warning("state: writing works again; journaling resumed from a fresh snapshot "
                    "(%d message(s) were not journaled meanwhile)", self.not_journaled)

    def failed(self, what: str, e: Exception) -> None:
        """A write of ``what`` (journal, snapshot) failed; counted (from the writer thread
        too), and logged if it is the first since writing last worked. A journal's failure
        suspends journaling at the worker's next round."""
        with self._lock:
            self.failures[what] += 1
            self.last_error = f"{what}: {e}"
            if what == "journal":
                self._broken = "journal"
            first, self._outage = not self._outage, True
        if first:
            log.error("state: writing the %s failed (%s); the robots are still served, and the "
                      "state is written again once there is room (journaling resumes from a "
                      "fresh snapshot); failures are counted in summary.json, not logged again",
                      what, e)

    def writer_failed(self, kind: str, e: Exception) -> None:
        """(the writer thread) Its journal sync or snapshot failed."""
        if kind == "snapshot":
            self._snapshot_failure(e)
        else:
            self.failed("journal", e)

    def _snapshot_failure(self, e: Exception) -> None:
        self.failed("snapshot", e)
        self.snapshots.reset()

    def _suspend(self) -> None:
        with self._lock:
            self._broken = None
        j, self.journal = self.journal, None
        if j is not None:
            self.bytes += j.bytes
            self.seconds += j.seconds
            with contextlib.suppress(Exception):
                j.close()
        self._next_try = time.monotonic() + self.retry_s

    def close(self) -> None:
        if self.journal is not None:
            try:
                self.journal.close()
            except OSError as e:
                self.failed("journal", e)

    def view(self) -> dict[str, Any]:
        """What the console shows (any thread)."""
        with self._lock:
            return {"writing": self.journal is not None,
                    "failures": sum(self.failures.values()),
                    "not_journaled": self.not_journaled, "last_error": self.last_error}

    def summary(self) -> dict[str, Any]:
        j = self.journal
        out: dict[str, Any] = {
            "entries": self.sequence, "bytes": self.bytes + (j.bytes if j else 0),
            "journal_s": round(self.seconds + (j.seconds if j else 0.0), 3),
            "snapshots": len(self.snapshot_s),
            "snapshot_s_max": round(max(self.snapshot_s, default=0.0), 3),
            "snapshot_s_total": round(sum(self.snapshot_s), 3),
            "snapshot_hold_ms_max": round(1e3 * max(self.snapshot_hold_s, default=0.0), 2),
            "snapshot_bytes": self.snapshots.last_bytes,
            "snapshot_bytes_total": self.snapshot_bytes,
            "writing": j is not None}
        if (pages := self.snapshots.huge_pages) is not None:
            out["huge_pages"] = ({"unavailable": pages.unavailable} if pages.unavailable else
                                 {"collapses": pages.runs, "seconds": round(pages.seconds, 3),
                                  "ranges_left": pages.refused})
        if self.failures:
            out |= {"failures": dict(self.failures), "not_journaled": self.not_journaled,
                    "resumed": self.resumed, "last_error": self.last_error}
        return out
