"""One thread that writes files for the server's worker, so the worker need not wait for disks:
snapshots (compressed, written and synced after the worker pickled them) and the refreshed
outputs (after the worker gathered them). One job of a kind at a time; a job submitted while
one of its kind still waits replaces it (the newer state is the one worth writing)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


class BackgroundWriter:
    def __init__(self, on_error: Callable[[str, Exception], None] | None = None,
                 name: str = "server-writer") -> None:
        self._jobs: dict[str, Callable[[], None]] = {}
        self._running: str | None = None
        self._cv = threading.Condition()
        self._closed = False
        self._on_error = on_error
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, kind: str, job: Callable[[], None]) -> None:
        with self._cv:
            if self._closed:
                raise RuntimeError("the writer is closed")
            self._jobs[kind] = job
            self._cv.notify_all()

    def busy(self, kind: str) -> bool:
        """Whether a job of ``kind`` waits or runs."""
        with self._cv:
            return kind in self._jobs or self._running == kind

    def drain(self, timeout_s: float = 60.0) -> bool:
        """Wait until every job submitted so far is done."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._jobs and self._running is None,
                                     timeout_s)

    def close(self, timeout_s: float = 60.0) -> None:
        self.drain(timeout_s)
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: bool(self._jobs) or self._closed)
                if not self._jobs:
                    return
                kind = next(iter(self._jobs))
                job = self._jobs.pop(kind)
                self._running = kind
            try:
                job()
            except Exception as e:   # a full disk must not stop the server
                if self._on_error is not None:
                    self._on_error(kind, e)     # counts and logs it as it sees fit
                else:
                    log.exception("writing %s failed", kind)
            finally:
                with self._cv:
                    self._running = None
                    self._cv.notify_all()
