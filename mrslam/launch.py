"""Start and stop mrslam's processes for a local run (the demo, benchmarks, end-to-end tests).

Each child runs in a session of its own (a terminal's Ctrl-C reaches the launcher only, which
stops the children in its order) and is told the launcher's pid (``MRSLAM_PARENT_PID``): it
stops by itself once the launcher has gone, however that went (``schemas.stopping``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from schemas.stopping import PARENT_ENV

log = logging.getLogger(__name__)


class GroupClosed(RuntimeError):
    """The group is stopping: it starts nothing any more."""


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen[bytes]
    log_path: Path
    args: tuple[str, ...] = ()
    #: the group was asked to stop it: an exit now is no failure
    stopping: bool = False
    #: environment variables it runs with beyond the group's own (kept across restarts)
    env: dict[str, str] = field(default_factory=dict)

    def alive(self) -> bool:
        return self.popen.poll() is None

    @property
    def pid(self) -> int:
        return self.popen.pid

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


@dataclass
class ProcessGroup:
    """Child processes whose output goes to ``<log_dir>/<name>.log``."""

    log_dir: Path
    procs: list[Proc] = field(default_factory=list)

    #: what a child runs: ``python -m mrslam ARGS`` (the same interpreter, so the same install)
    command: tuple[str, ...] = (sys.executable, "-m", "mrslam")
    #: set by ``terminate_all``: nothing is started or restarted any more
    closed: bool = False
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def start(self, name: str, *args: str, env: dict[str, str] | None = None) -> Proc:
        """Run ``command ARGS``, its output going to ``<log_dir>/<name>.log``; ``env``: more
        environment variables (a secret that must not show in the process list)."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        path = self.log_dir / f"{name}.log"
        with self._lock:   # started and listed at once: terminate_all sees every child
            self._refuse_when_closed(name)
            p = Proc(name, self._spawn(path, args, "wb", env or {}), path, args,
                     env=dict(env or {}))
            self.procs.append(p)
        log.info("started %s (pid %d)", name, p.pid)
        return p

    def restart(self, p: Proc, args: tuple[str, ...] | None = None) -> None:
        """Start ``p``'s command again in its place (``p`` must have exited); its log goes on
        in the same file. ``args``: run these instead from now on."""
        if p.alive():
            raise RuntimeError(f"{p.name} (pid {p.pid}) is still running")
        with p.log_path.open("ab") as out:
            out.write(f"\n--- {time.strftime('%H:%M:%S')} restarted after exit code "
                      f"{p.popen.returncode} ---\n".encode())
        old = p.pid
        if args is not None:
            p.args = args
        with self._lock:
            self._refuse_when_closed(p.name)
            p.popen = self._spawn(p.log_path, p.args, "ab", p.env)
        log.info("restarted %s (pid %d, was %d)", p.name, p.pid, old)

    def _spawn(self, log_path: Path, args: tuple[str, ...], mode: str,
               extra_env: dict[str, str]) -> subprocess.Popen[bytes]:
        env = dict(os.environ, PYTHONUNBUFFERED="1", **extra_env)
        env[PARENT_ENV] = str(os.getpid())
        with log_path.open(mode) as out:
            return subprocess.Popen([*self.command, *args], stdout=out,
                                    stderr=subprocess.STDOUT, env=env, start_new_session=True)

    def _refuse_when_closed(self, name: str) -> None:
        if self.closed:
            raise GroupClosed(f"not starting {name}: the run is stopping")

    def terminate_all(self, kill_after_s: float) -> None:
        """Stop every child at once and start nothing more: SIGTERM now, and SIGKILL (to its
        whole process group: a server's planner processes too) whatever is still there
        ``kill_after_s`` later. Returns at once (a signal's thread calls it)."""
        with self._lock:
            self.closed = True
            chosen = list(self.procs)
            for p in chosen:
                p.stopping = True
        for p in chosen:
            if p.alive():
                with contextlib.suppress(ProcessLookupError):
                    p.popen.send_signal(signal.SIGTERM)
        threading.Thread(target=self._kill_after, args=(chosen, kill_after_s),
                         name="kill-after", daemon=True).start()

    @staticmethod
    def _kill_after(chosen: list[Proc], kill_after_s: float) -> None:
        deadline = time.monotonic() + kill_after_s
        while time.monotonic() < deadline and any(p.alive() for p in chosen):
            time.sleep(0.05)
        for p in chosen:
            if p.alive():
                log.warning("%s did not stop within %.1f s; killing it", p.name, kill_after_s)
            # the whole group, even when its leader has gone: what it started goes too
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.popen.pid, signal.SIGKILL)

    def stop(self, names: list[str] | None = None, timeout_s: float = 15.0) -> None:
        """SIGTERM, then SIGKILL whatever has not exited after ``timeout_s``."""
        chosen = [p for p in self.procs if names is None or p.name in names]
        for p in chosen:
            p.stopping = True
            if p.alive():
                with contextlib.suppress(ProcessLookupError):
                    p.popen.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for p in chosen:
            left = max(0.1, deadline - time.monotonic())
            try:
                p.popen.wait(timeout=left)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s; killing it", p.name, timeout_s)
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.popen.pid, signal.SIGKILL)
                p.popen.wait(timeout=5)

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
