"""A pseudo-terminal that behaves like the base's microcontroller (deploy/firmware/base).

It follows the documented frame protocol as the sketch does: SPEED frames set the wheel speeds
[ticks/s] for their timeout, STOP and any frame with a bad checksum stop the motors, and every
20 ms it reports the cumulative encoder ticks of wheels that follow the set speeds exactly.
Every change of the motor output is logged with its time, so tests can check when it stopped.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from pathlib import Path

from robot_agent.drivers import base_protocol as proto
from robot_agent.drivers.fakes.pty_link import point_link


class FakeMicrocontroller:
    def __init__(self, link: Path, period_s: float = 0.02) -> None:
        self.link = link
        self.period_s = period_s
        self.speed = (0, 0)                     # ticks/s being driven
        self.ticks = [0.0, 0.0]
        self.motor_log: list[tuple[float, tuple[int, int]]] = [(time.monotonic(), (0, 0))]
        self.received: list[proto.Frame] = []
        self.bad_frames = 0
        self.corrupt_next = False
        self._deadline = 0.0
        self._flags = 0
        self._t0 = time.monotonic()
        self._lock = threading.Lock()
        self._fds: tuple[int, int] | None = None
        self._stop = threading.Event()
        self.plug()
        self._thread = threading.Thread(target=self._run, daemon=True, name="fake-mcu")
        self._thread.start()

    def plug(self, restart: bool = True) -> None:
        """Connect a new pty behind ``link``; ``restart``: the board rebooted (counters at 0)."""
        master, slave = os.openpty()
        tty.setraw(slave)
        with self._lock:
            self._fds = (master, slave)
            if restart:
                self.ticks = [0.0, 0.0]
                self._t0 = time.monotonic()
        point_link(self.link, slave)

    def unplug(self) -> None:
        with self._lock:
            fds, self._fds = self._fds, None
        self._set((0, 0))          # USB power gone
        for fd in fds or ():
            os.close(fd)
        self.link.unlink(missing_ok=True)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.unplug()

    def stopped_since(self) -> float | None:
        """Monotonic time the motors last stopped (None while driving)."""
        t, speed = self.motor_log[-1]
        return t if speed == (0, 0) else None

    def _set(self, speed: tuple[int, int]) -> None:
        if speed != self.speed:
            self.speed = speed
            self.motor_log.append((time.monotonic(), speed))

    def _run(self) -> None:
        parser = proto.FrameParser()
        seq = 0
        last = next_report = time.monotonic()
        while not self._stop.is_set():
            fds = self._fds
            if fds is None:
                time.sleep(0.01)
                continue
            master = fds[0]
            try:
                ready, _, _ = select.select([master], [], [], 0.005)
                data = os.read(master, 4096) if ready else b""
                bad = parser.bad_frames
                for f in parser.feed(data):
                    self.received.append(f)
                    if f.kind == proto.SPEED:
                        left, right, timeout_ms = proto.parse_speed(f)
                        self._deadline = time.monotonic() + timeout_ms / 1000
                        self._set((left, right))
                    elif f.kind == proto.STOP:
                        self._set((0, 0))
                if parser.bad_frames != bad:
                    self.bad_frames += parser.bad_frames - bad
                    self._flags |= proto.FLAG_BAD_FRAME
                    self._set((0, 0))
                now = time.monotonic()
                if self.speed != (0, 0) and now > self._deadline:
                    self._flags |= proto.FLAG_TIMEOUT
                    self._set((0, 0))
                self.ticks[0] += self.speed[0] * (now - last)
                self.ticks[1] += self.speed[1] * (now - last)
                last = now
                if now >= next_report:
                    next_report = now + self.period_s
                    seq += 1
                    flags = self._flags | (proto.FLAG_DRIVING if self.speed != (0, 0) else 0)
                    self._flags = 0
                    out = proto.Encoders(int((now - self._t0) * 1000), round(self.ticks[0]),
                                         round(self.ticks[1]), flags).encode(seq)
                    if self.corrupt_next:
                        self.corrupt_next = False
                        out = out[:-1] + bytes((out[-1] ^ 0x5A,))
                    os.write(master, out)
            except OSError:
                time.sleep(0.01)
