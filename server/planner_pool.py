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
