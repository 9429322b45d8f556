"""The processes that replan and decide for the server's navigators (``server.exploration.
replan``): started with ``spawn`` (the server runs threads; forking them is unsafe), and tied to
the server's life — a server killed with SIGKILL takes them along instead of leaving orphans."""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

PR_SET_PDEATHSIG = 1


def start(processes: int) -> ProcessPoolExecutor:
    """A pool of ``processes`` planner processes, each importing the planner at once."""
    pool = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_follow_parent, initargs=(os.getpid(),))
    for _ in range(processes):
        pool.submit(_warm)
    return pool


def stop(pool: ProcessPoolExecutor) -> None:
    """End the pool at once: jobs not started are dropped, and the processes are killed
    rather than waited for (a replan or a map query holds nothing of the server's state; its
    answer is no longer wanted), so a stopping server never waits on a job."""
    # the executor's own processes and thread (Python 3.14's kill_workers() does this);
    # read first: shutdown forgets them
    processes = dict(getattr(pool, "_processes", None) or {})
    manager = getattr(pool, "_executor_manager_thread", None)
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes.values():
        with contextlib.suppress(Exception):
            proc.kill()
    for proc in processes.values():
        with contextlib.suppress(Exception):
            proc.join(timeout=2.0)
    if manager is not None:   # it sees them gone and ends
        manager.join(timeout=2.0)


def _follow_parent(parent_pid: int) -> None:
    """In a planner process: end when the server ends, however it ends."""
    if sys.platform.startswith("linux"):   # the kernel kills us when the parent dies
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent_pid:    # it died before that took hold
        os._exit(0)

    def watch() -> None:              # elsewhere (and as a second line): look every second
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _warm() -> None:
    import server.exploration.replan  # noqa: F401  (what the jobs run)


class Pools:
    """The processes the core's slow work runs in, given to the core once: replanning and
    lone robots' decisions (``planner``), map matching between teams (``matcher``). Each is
    started at its first need, and there is none (the work runs in line) in lockstep, where
    a run must not depend on how fast they answer, or with ``planner_processes: 0``."""

    def __init__(self, processes: int, map_match: bool, lockstep: Callable[[], bool]) -> None:
        self.processes = processes
        self.map_match = map_match
        self._lockstep = lockstep
        self._planner: ProcessPoolExecutor | None = None
        self._matcher: ProcessPoolExecutor | None = None

    def planner(self) -> ProcessPoolExecutor | None:
        if self._lockstep() or self.processes == 0:
            return None
        if self._planner is None:
            self._planner = start(self.processes)
        return self._planner

    def matcher(self, teams: int) -> ProcessPoolExecutor | None:
        """Map matching's own process (a query of a second or two never holds up the robots'
        decisions), started once there are ``teams`` >= 2 to match."""
        if self._lockstep() or self.processes == 0 or not self.map_match:
            return None
        if self._matcher is None and teams >= 2:
            self._matcher = start(1)
        return self._matcher

    def stop(self) -> None:
        for pool in (self._planner, self._matcher):
            if pool is not None:
                stop(pool)      # killed, not waited for: no job holds the stop up
        self._planner = self._matcher = None
