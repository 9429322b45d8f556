"""How a process is asked to stop, and how it ends when it does not: the shared rules of the
server, the demo and the processes the demo starts.

``SignalStop``: SIGINT and SIGTERM (and SIGHUP, unless it is ignored as ``nohup`` does) set an
event at once. Python runs its signal handlers on the main thread between bytecodes, so a
main thread waiting inside a library call (a Zenoh session that is still connecting) would
hold a handler back for as long as that call lasts; here a thread of our own reads the
signal's number from the wakeup descriptor instead, sets the event and runs the callbacks.
With ``exit_after_s`` the process ends that long after the first signal whatever it is doing
(the server's state is written to survive a SIGKILL anyway, docs/state-and-recovery.md).

``follow_parent``: a process started by a launcher that names itself in ``MRSLAM_PARENT_PID``
asks itself to stop (SIGTERM) once that parent has gone, however it went (SIGKILL too), and
ends ``grace_s`` later if that did not do it. It watches ``getppid()``, not the kernel's
``PR_SET_PDEATHSIG``: that signal follows the parent *thread* that started the child, and the
demo starts agents again from a thread of its own (a reboot), which ends long before the run.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import Any

log = logging.getLogger(__name__)

#: the launcher's pid, in a child's environment (read and removed at the child's start)
PARENT_ENV = "MRSLAM_PARENT_PID"

#: callback(signal number, how many stop signals so far)
OnSignal = Callable[[int, int], None]


def _stop_signals() -> list[int]:
    sigs: list[int] = [signal.SIGINT, signal.SIGTERM]
    if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:
        sigs.append(signal.SIGHUP)    # nohup: the user asked for the run to outlive the terminal
    return sigs


class SignalStop:
    """A stop asked by a signal (main thread only; elsewhere it never fires). Use as a
    context manager: the previous handlers come back on exit."""

    def __init__(self, event: threading.Event | None = None, exit_after_s: float | None = None,
                 exit_code: int = 1, name: str = "the process") -> None:
        self.event = event if event is not None else threading.Event()
        self.exit_after_s = exit_after_s
        self.exit_code = exit_code
        self.name = name
        #: the first stop signal, or None
        self.signum: int | None = None
        self.count = 0
        self._callbacks: list[OnSignal] = []
        self._lock = threading.Lock()
        self._previous: dict[int, Any] = {}
        self._previous_fd: int | None = None
        self._pair: tuple[socket.socket, socket.socket] | None = None
        self._left = threading.Event()    # the with block has ended: no deadline any more

    @property
    def signal_name(self) -> str:
        return "" if self.signum is None else signal.Signals(self.signum).name

    def on_signal(self, fn: OnSignal) -> None:
        """Call ``fn`` on every stop signal from now on, on the watching thread; at once when
        one came already."""
        with self._lock:
            self._callbacks.append(fn)
            came = self.signum, self.count
        if came[0] is not None:
            fn(came[0], came[1])

    def __enter__(self) -> SignalStop:
        if threading.current_thread() is not threading.main_thread():
            return self
        reader, writer = socket.socketpair()
        writer.setblocking(False)
        self._pair = (reader, writer)
        threading.Thread(target=self._watch, args=(reader,), name="signal-stop",
                         daemon=True).start()
        self._previous_fd = signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
        for sig in _stop_signals():
            # the C handler writes the number to the wakeup descriptor; the work is ours
            self._previous[sig] = signal.signal(sig, _noted)
        return self

    def __exit__(self, *exc: object) -> None:
        self._left.set()
        if self._pair is None:
            return
        for sig, old in self._previous.items():
            signal.signal(sig, old if old is not None else signal.SIG_DFL)
        signal.set_wakeup_fd(self._previous_fd if self._previous_fd is not None else -1)
        reader, writer = self._pair
        self._pair = None
        with contextlib.suppress(OSError):
            reader.shutdown(socket.SHUT_RDWR)
        writer.close()

    def _watch(self, reader: socket.socket) -> None:
        while True:
            try:
                data = reader.recv(64)
            except OSError:
                data = b""
            if not data:
                reader.close()
                return
            for signum in data:
                if signum in self._previous:
                    self._fire(signum)

    def _fire(self, signum: int) -> None:
        with self._lock:
            self.count += 1
            if self.signum is None:
                self.signum = signum
            callbacks, count = list(self._callbacks), self.count
        self.event.set()
        if count == 1:
            log.warning("%s: stopping (%s)", self.name, signal.Signals(signum).name)
            if self.exit_after_s is not None:
                threading.Thread(target=self._exit_later, name="stop-deadline",
                                 daemon=True).start()
        for fn in callbacks:
            try:
                fn(signum, count)
            except Exception:   # one callback's failure must not keep the others from stopping
                log.exception("stopping: a callback failed")

    def _exit_later(self) -> None:
        assert self.exit_after_s is not None
        if self._left.wait(self.exit_after_s):
            return
        log.error("%s did not stop within %.1f s of the signal; exiting now", self.name,
                  self.exit_after_s)
        for h in logging.getLogger().handlers:
            with contextlib.suppress(Exception):
                h.flush()
        os._exit(self.exit_code)


def _noted(signum: int, frame: FrameType | None) -> None:
    """The Python-level handler: nothing to do (the wakeup descriptor carries the signal)."""


def follow_parent(poll_s: float = 0.25, grace_s: float = 5.0) -> int | None:
    """In a child: stop when the launcher named in ``MRSLAM_PARENT_PID`` has gone (see the
    module's docstring). The variable is removed, so this process's own children do not
    follow its parent. Returns the parent's pid, or None when none was named."""
    raw = os.environ.pop(PARENT_ENV, None)
    try:
        parent = int(raw) if raw else None
    except ValueError:
        parent = None
    if parent is None:
        return None

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        log.warning("the process that started this one (pid %d) has gone: stopping", parent)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(grace_s)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    return parent
