"""Keep a child process running as systemd's ``Restart=on-failure`` would.

A child that exits with code 0, or after its group was asked to stop it, is done. Any other
exit (a non-zero code, or a signal such as SIGKILL from the OOM killer) is a failure: the
child is started again with the same command after a back-off that doubles with each restart
(``back_off_s``, 2 × ``back_off_s``, … at most ``MAX_BACK_OFF_S``), at most ``max_restarts``
times. Every failure is recorded (``Exit``), whether or not it was restarted.

``Supervisor.poll`` never blocks: the caller's loop calls it as often as it checks anything
else, so the back-off runs while the rest of the run goes on.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from mrslam.launch import Proc, ProcessGroup

log = logging.getLogger(__name__)

#: the longest wait before a restart [s]
MAX_BACK_OFF_S = 30.0

State = Literal["running", "restarting", "done", "failed"]


@dataclass(frozen=True)
class RestartPolicy:
    max_restarts: int = 5
    back_off_s: float = 1.0

    def back_off(self, restarts_so_far: int) -> float:
        """The wait before restart number ``restarts_so_far + 1`` [s]."""
        return float(min(self.back_off_s * 2.0 ** restarts_so_far, MAX_BACK_OFF_S))


@dataclass
class Exit:
    """One unexpected exit of the child. Times are monotonic seconds (``time.monotonic``)."""

    pid: int
    exit_code: int
    signal: str | None            # the signal that ended it, e.g. SIGKILL
    exited_at: float              # when the exit was noticed
    sim_time_s: float | None      # the run's simulated time then, when known
    back_off_s: float | None = None   # the wait before its restart; None: budget spent
    restarted: bool = False           # the restart happened (not when the run ended first)
    restarted_at: float | None = None
    new_pid: int | None = None


def signal_name(exit_code: int | None) -> str | None:
    """``SIGKILL`` for a Popen return code of −9; None for a normal exit."""
    if exit_code is None or exit_code >= 0:
        return None
    try:
        return signal.Signals(-exit_code).name
    except ValueError:
        return f"signal {-exit_code}"


class Supervisor:
    """Restarts ``proc`` of ``group`` when it fails, following ``policy``."""

    def __init__(self, group: ProcessGroup, proc: Proc, policy: RestartPolicy,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.group, self.proc, self.policy, self.clock = group, proc, policy, clock
        self.exits: list[Exit] = []
        self._due: float | None = None   # when the pending restart is due

    @property
    def restarts(self) -> int:
        """Restarts done or due."""
        return sum(1 for e in self.exits if e.back_off_s is not None)

    def poll(self, sim_time_s: float | None = None) -> State:
        """Check the child; restart it when its back-off is over. ``sim_time_s`` is recorded
        with an exit noticed now."""
        now = self.clock()
        if self.proc.stopping:
            self._due = None
        if self._due is not None:
            if now < self._due:
                return "restarting"
            self.group.restart(self.proc)
            self._due = None
            last = self.exits[-1]
            last.restarted, last.restarted_at, last.new_pid = True, now, self.proc.pid
            return "running"
        code = self.proc.popen.poll()
        if code is None:
            return "running"
        if code == 0 or self.proc.stopping:
            return "done"
        if self.exits and self.exits[-1].pid == self.proc.pid:
            return "failed"   # noticed before; the budget was spent
        wait = (self.policy.back_off(self.restarts)
                if self.restarts < self.policy.max_restarts else None)
        self.exits.append(Exit(pid=self.proc.pid, exit_code=code, signal=signal_name(code),
                               exited_at=now, sim_time_s=sim_time_s, back_off_s=wait))
        how = signal_name(code) or f"exit code {code}"
        if wait is None:
            log.error("%s (pid %d) died (%s) after %d restart(s); not restarting it",
                      self.proc.name, self.proc.pid, how, self.restarts)
            return "failed"
        log.warning("%s (pid %d) died (%s); restart %d of %d in %g s", self.proc.name,
                    self.proc.pid, how, self.restarts, self.policy.max_restarts, wait)
        self._due = now + wait
        return "restarting"
