"""The planner processes live and die with the server: a server killed with SIGKILL leaves no
orphan behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from tests.waiting import within

SERVER_LIKE = """
import os, sys, time
from server.runtime import planner_pool
pool = planner_pool.start(2)
pool.submit(os.getpid).result()
print(" ".join(str(p) for p in pool._processes), flush=True)
time.sleep(60)
"""


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    state = Path(f"/proc/{pid}/stat").read_text().split()[2] if Path(f"/proc/{pid}").exists() \
        else "X"
    return state not in ("Z", "X")


def test_planner_processes_end_with_a_killed_server() -> None:
    proc = subprocess.Popen([sys.executable, "-c", SERVER_LIKE], stdout=subprocess.PIPE,
                            cwd=Path(__file__).resolve().parents[1], text=True)
    try:
        assert proc.stdout is not None
        children = [int(p) for p in proc.stdout.readline().split()]
        assert len(children) == 2 and all(alive(p) for p in children)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        assert within(lambda: not any(alive(p) for p in children), 10.0)
    finally:
        if proc.poll() is None:
            proc.kill()
