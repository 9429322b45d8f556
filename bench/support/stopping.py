"""Stopping a run from outside, as systemd, a CI runner or a user's ``kill`` does.

A ``mrslam`` command is started with a tag in its environment; every process it starts
inherits the environment (the server's planner processes and a console's browser too), so
the processes of the run are found by their tag in ``/proc/<pid>/environ`` wherever they
were re-parented after their parent died. ``stop`` sends one signal to the command and
follows the run's processes until none is left.

"Without a terminal" (``sigint_ignored``) is how a shell starts a background job: in its own
session, with SIGINT ignored (which an exec keeps). SIGHUP is left as a terminal leaves it
(not ignored), whatever the caller has (``nohup``).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
TAG_ENV = "MRSLAM_BENCH_RUN"

#: the command with SIGHUP as a terminal leaves it (whatever this process has, e.g. under
#: nohup) and SIGINT as given: ignored for a shell's background job (exec keeps both)
_EXEC = ("import os, signal, sys; signal.signal(signal.SIGHUP, signal.SIG_DFL); "
         "signal.signal(signal.SIGINT, signal.SIG_IGN if sys.argv[1] == 'ignore' "
         "else signal.SIG_DFL); "
         "os.execv(sys.executable, [sys.executable, '-m', 'mrslam', *sys.argv[2:]])")


def tagged(tag: str) -> dict[int, str]:
    """The live processes (not zombies) whose environment carries ``tag``: pid -> what runs
    (the ``mrslam`` command, or the program's name)."""
    needle = f"{TAG_ENV}={tag}".encode()
    found: dict[int, str] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if needle not in (entry / "environ").read_bytes().split(b"\0"):
                continue
            stat = (entry / "stat").read_text()
            if stat.rsplit(")", 1)[1].split()[0] in ("Z", "X"):
                continue      # exited, waiting for its parent to collect it
            found[int(entry.name)] = _what(entry)
        except OSError:       # gone meanwhile
            continue
    return found


def _what(entry: Path) -> str:
    argv = (entry / "cmdline").read_bytes().split(b"\0")
    words = [a.decode(errors="replace") for a in argv if a]
    if "mrslam" in words:
        rest = words[words.index("mrslam") + 1:]
        return " ".join(["mrslam", *rest[:1]])
    if any("multiprocessing" in w for w in words):
        return "python (multiprocessing)"
    return Path(words[0]).name if words else "?"


@dataclass
class Run:
    """A ``mrslam`` command started with a tag of its own."""

    proc: subprocess.Popen[bytes]
    tag: str
    log_path: Path
    started: float = field(default_factory=time.monotonic)

    def processes(self) -> dict[int, str]:
        return tagged(self.tag)

    def wait_for(self, count: int, timeout_s: float) -> bool:
        """Whether the run has ``count`` processes at once within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if len(self.processes()) >= count:
                return True
            if self.proc.poll() is not None:
                return False
            time.sleep(0.2)
        return False

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def start(args: list[str], log_path: Path, *, sigint_ignored: bool = False,
          env: dict[str, str] | None = None) -> Run:
    """``python -m mrslam ARGS`` in a session of its own, without a terminal."""
    tag = uuid.uuid4().hex
    cmd = [sys.executable, "-c", _EXEC, "ignore" if sigint_ignored else "default", *args]
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdin=subprocess.DEVNULL, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT), TAG_ENV: tag,
                                     **(env or {})})
    return Run(proc, tag, log_path)


def stop(run: Run, sig: signal.Signals, within_s: float = 5.0, give_up_s: float = 90.0
         ) -> dict[str, Any]:
    """Send ``sig`` to the command and follow its run's processes: how many were alive then,
    which were still alive ``within_s`` later, when the last one ended (None: still alive
    after ``give_up_s``) and when the command itself exited. Whatever is left after
    ``give_up_s`` is killed (and counted)."""
    before = run.processes()
    t0 = time.monotonic()
    run.proc.send_signal(sig)
    at_deadline: dict[int, str] | None = None
    all_gone_s = command_exit_s = None
    while time.monotonic() - t0 < give_up_s:
        now = time.monotonic() - t0
        if command_exit_s is None and run.proc.poll() is not None:
            command_exit_s = now
        left = run.processes()
        if at_deadline is None and now >= within_s:
            at_deadline = left
        if not left:
            all_gone_s = now
            if command_exit_s is None:
                command_exit_s = now
            break
        time.sleep(0.05)
    if at_deadline is None:
        at_deadline = {}
    leftovers = run.processes()
    for pid in leftovers:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    run.proc.wait()
    return {"signal": sig.name, "processes_at_signal": len(before),
            "kinds_at_signal": sorted(before.values()),
            f"alive_after_{within_s:g}_s": sorted(at_deadline.values()),
            "all_gone_s": None if all_gone_s is None else round(all_gone_s, 2),
            "command_exit_s": None if command_exit_s is None else round(command_exit_s, 2),
            "exit_code": run.proc.returncode, "killed_after_give_up": len(leftovers)}
