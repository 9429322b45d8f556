"""A pseudo-terminal that behaves like the camera tower's stepper controller.

It speaks ``robot_agent.drivers.tower_protocol``: a stepper that makes ``step_rate`` microsteps
a second, a reference trigger (an optical slot ``slot`` microsteps wide) lit where the rotor's
physical position is ``trigger_step`` … ``trigger_step + slot − 1`` modulo a turn, and the
silence rule: no valid host line for ``timeout_s`` while the coils are energised stops the
motor, de-energises it (the rotor may slip: the position is no longer known, state UNHOMED) and
reports TIMEOUT. The controller counts steps (``count``); the rotor's ``physical`` position
follows it exactly, except where a fault is injected:

- ``trigger_broken``: the slot never lights (homing fails with ERR NOTRIGGER);
- ``inject(data)``: bytes slipped into the line to the host (garbage, broken lines);
- ``lose_steps(n)``: the rotor slips ``n`` microsteps without the count knowing; the check of
  the trigger at every step then finds the disagreement (ERR POSITION).
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from pathlib import Path

from robot_agent.drivers import tower_protocol as proto
from robot_agent.drivers.fakes.pty_link import point_link


class FakeTowerController:
    def __init__(self, link: Path, steps_per_rev: int = 6400, trigger_step: int = 1234,
                 slot: int = 8, step_rate: float = 100_000.0, timeout_s: float = 0.4,
                 physical: int = 0) -> None:
        self.link = link
        self.steps_per_rev, self.trigger_step, self.slot = steps_per_rev, trigger_step, slot
        self.step_rate, self.timeout_s = step_rate, timeout_s
        self.physical = physical           # where the rotor really is [microsteps]
        self.count = 0                     # where the controller thinks it is
        self.target = 0
        self.state = "UNHOMED"
        self.energised = False
        self.trigger_broken = False
        self.homes = 0                     # HOMED reports
        self.timeouts = 0                  # stops on silence
        self.stopped_at: float | None = None   # monotonic time of the last stop on silence
        self.position_errors = 0
        self.bad_commands = 0
        self.received: list[tuple[str, int | None]] = []
        self._homing_steps = 0
        self._was_lit = False
        self._lock = threading.Lock()
        self._inject = bytearray()
        self._last_valid = time.monotonic()
        self._fds: tuple[int, int] | None = None
        self._stop = threading.Event()
        master, slave = os.openpty()
        tty.setraw(slave)
        self._fds = (master, slave)
        point_link(self.link, slave)
        self._thread = threading.Thread(target=self._run, daemon=True, name="fake-tower")
        self._thread.start()

    # -- the test's hands -------------------------------------------------------------------
    def inject(self, data: bytes) -> None:
        with self._lock:
            self._inject += data

    def lose_steps(self, n: int) -> None:
        with self._lock:
            self.physical += n

    def lit(self) -> bool:
        """Whether the reference trigger sees its flag at the rotor's physical position."""
        if self.trigger_broken:
            return False
        return (self.physical - self.trigger_step) % self.steps_per_rev < self.slot

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        with self._lock:
            fds, self._fds = self._fds, None
        for fd in fds or ():
            os.close(fd)
        self.link.unlink(missing_ok=True)

    # -- the controller ---------------------------------------------------------------------
    def _run(self) -> None:
        splitter = proto.LineSplitter()
        last = time.monotonic()
        budget = 0.0
        while not self._stop.is_set():
            fds = self._fds
            if fds is None:
                return
            master = fds[0]
            out = bytearray()
            try:
                ready, _, _ = select.select([master], [], [], 0.002)
                data = os.read(master, 4096) if ready else b""
            except OSError:
                time.sleep(0.01)
                continue
            with self._lock:
                for line in splitter.feed(data):
                    out += self._command(line)
                now = time.monotonic()
                if self.state in ("HOMING", "MOVING"):
                    budget = min(budget + (now - last) * self.step_rate, 10_000.0)
                    n = int(budget)
                    budget -= n
                    out += self._steps(n)
                else:
                    budget = 0.0
                last = now
                if self.energised and now - self._last_valid > self.timeout_s:
                    self.energised = False
                    self.state = "UNHOMED"
                    self.timeouts += 1
                    self.stopped_at = now
                    out += proto.encode("TIMEOUT", self.count)
                if self._inject:
                    out[0:0] = self._inject
                    self._inject.clear()
            if out:
                try:
                    os.write(master, bytes(out))
                except OSError:
                    time.sleep(0.01)

    def _command(self, line: bytes) -> bytes:
        try:
            cmd, arg = proto.parse_command(line)
        except proto.TowerProtocolError:
            self.bad_commands += 1
            return proto.encode("ERR", "BADCMD", 0)
        self._last_valid = time.monotonic()
        self.received.append((cmd, arg))
        if cmd == "PING":
            return proto.encode("PONG", self.count, self.state)
        if cmd == "POS":
            return proto.encode("POS", self.count, self.target, self.state)
        if cmd == "STOP":
            if self.state in ("HOMING", "MOVING"):
                self.state = "READY" if self.state == "MOVING" else "UNHOMED"
            self.target = self.count
            return proto.encode("ACK", "STOP")
        if self.state in ("HOMING", "MOVING"):
            return proto.encode("ERR", "BUSY", 0)
        if cmd == "HOME":
            self.energised = True
            self.state = "HOMING"
            self._homing_steps = 0
            self._was_lit = self.lit()
            return proto.encode("ACK", "HOME")
        assert arg is not None              # MOVE
        if self.state != "READY":
            return proto.encode("ERR", "NOTHOMED", 0)
        if abs(arg) > 10 * self.steps_per_rev:
            return proto.encode("ERR", "RANGE", arg)
        self.target = arg
        if arg == self.count:
            return proto.encode("ACK", "MOVE") + proto.encode("DONE", self.count)
        self.state = "MOVING"
        return proto.encode("ACK", "MOVE")

    def _steps(self, n: int) -> bytes:
        for _ in range(n):
            if self.state == "HOMING":
                self.physical += 1
                self.count += 1
                self._homing_steps += 1
                now_lit = self.lit()
                if now_lit and not self._was_lit:
                    fired_at = self.count
                    self.count = self.target = 0
                    self.state = "READY"
                    self.homes += 1
                    return proto.encode("HOMED", fired_at)
                self._was_lit = now_lit
                if self._homing_steps > self.steps_per_rev + self.slot:
                    self.state = "UNHOMED"
                    return proto.encode("ERR", "NOTRIGGER", self._homing_steps)
            else:
                d = 1 if self.target > self.count else -1
                self.physical += d
                self.count += d
                expect = self.count % self.steps_per_rev < self.slot
                if self.lit() != expect:
                    self.state = "UNHOMED"
                    self.target = self.count
                    self.position_errors += 1
                    return proto.encode("ERR", "POSITION", self.count)
                if self.count == self.target:
                    self.state = "READY"
                    return proto.encode("DONE", self.count)
        return b""
