"""A pseudo-terminal that behaves like an RPLIDAR A2 (for tests, bench/agent.py and trying the
agent without the device).

The device end of a pty answers requests with byte strings built from the protocol
specification (``robot_agent.drivers.rplidar_protocol`` encoders, which the tests check against
hand-written bytes) and streams scan nodes in real time. The driver opens a symlink to the pty,
so "unplugging" (closing the pty) and "replugging" (a new pty behind the same name) look to it
like a USB device going away and coming back under its udev name.
"""

from __future__ import annotations

import math
import os
import select
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

from robot_agent.drivers import rplidar_protocol as proto
from robot_agent.drivers.fakes.pty_link import point_link

BANNER = b"RP LIDAR System.\r\nFirmware Ver 1.29 - rtm, HW Ver 7\r\nModel: 44\r\n"
INFO = proto.DeviceInfo(model=44, firmware=(1, 29), hardware=7,
                        serial_number="0123456789ABCDEF0123456789ABCDEF")


def circle_room(angle_deg: float) -> float:
    return 2000.0


class FakeRplidar:
    def __init__(self, link: Path, distance_mm: Callable[[float], float] = circle_room,
                 nodes_per_rev: int = 360, rev_hz: float = 10.0, health: int = 0) -> None:
        self.link = link
        self.distance_mm = distance_mm
        self.nodes_per_rev, self.rev_hz = nodes_per_rev, rev_hz
        self.health_status = health
        self.requests: list[int] = []
        self.streaming = False
        self.revolutions = 0
        self._lock = threading.Lock()
        self._inject = bytearray()
        self._master: int | None = None
        self._slave: int | None = None
        self._stop = threading.Event()
        self._index = 0
        self._due = 0.0
        self.plug()
        self._thread = threading.Thread(target=self._run, daemon=True, name="fake-rplidar")
        self._thread.start()

    # -- the cable --------------------------------------------------------------------------
    def plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        with self._lock:
            self._master, self._slave = master, slave
            self.streaming = False
        point_link(self.link, slave)

    def unplug(self) -> None:
        with self._lock:
            fds = [fd for fd in (self._master, self._slave) if fd is not None]
            self._master = self._slave = None
            self.streaming = False
        for fd in fds:
            os.close(fd)
        self.link.unlink(missing_ok=True)

    def inject(self, data: bytes) -> None:
        """Bytes to slip into the stream (line noise)."""
        with self._lock:
            self._inject += data

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.unplug()

    # -- the device -------------------------------------------------------------------------
    def _run(self) -> None:
        buf = bytearray()
        last = time.monotonic()
        while not self._stop.is_set():
            master = self._master
            if master is None:
                time.sleep(0.01)
                continue
            try:
                ready, _, _ = select.select([master], [], [], 0.01)
                if ready:
                    buf += os.read(master, 4096)
                    self._handle(master, buf)
                now = time.monotonic()
                self._stream(master, now - last)
                last = now
            except OSError:  # unplugged under us
                time.sleep(0.01)

    def _handle(self, fd: int, buf: bytearray) -> None:
        while buf:
            if buf[0] != proto.SYNC:
                del buf[0]
                continue
            if len(buf) < 2:
                return
            cmd = buf[1]
            if cmd >= 0x80:
                if len(buf) < 3 or len(buf) < 4 + buf[2]:
                    return
                del buf[:4 + buf[2]]
            else:
                del buf[:2]
            self.requests.append(cmd)
            if cmd == proto.CMD_STOP:
                self.streaming = False
            elif cmd == proto.CMD_RESET:
                self.streaming = False
                self.health_status = 0
                os.write(fd, BANNER)
            elif cmd == proto.CMD_GET_INFO:
                os.write(fd, proto.Descriptor(proto.INFO_LEN, proto.MODE_SINGLE,
                                              proto.TYPE_INFO).encode() + INFO.encode())
            elif cmd == proto.CMD_GET_HEALTH:
                os.write(fd, proto.Descriptor(proto.HEALTH_LEN, proto.MODE_SINGLE,
                                              proto.TYPE_HEALTH).encode()
                         + bytes((self.health_status, 0x34, 0x12)))
            elif cmd == proto.CMD_SCAN:
                os.write(fd, proto.Descriptor(proto.NODE_LEN, proto.MODE_MULTIPLE,
                                              proto.TYPE_SCAN).encode())
                self.streaming, self._index, self._due = True, 0, 0.0

    def _stream(self, fd: int, dt: float) -> None:
        if not self.streaming:
            return
        self._due += dt * self.nodes_per_rev * self.rev_hz
        n = int(self._due)
        self._due -= n
        out = bytearray()
        for _ in range(n):
            i = self._index % self.nodes_per_rev
            if i == 0 and self._index:
                self.revolutions += 1
            angle = 360.0 * i / self.nodes_per_rev
            d = self.distance_mm(angle)
            out += proto.encode_node(i == 0, 15 if d > 0 else 0, angle, d)
            self._index += 1
        with self._lock:
            if self._inject:
                cut = len(out) // 2 - (len(out) // 2) % proto.NODE_LEN
                out[cut:cut] = self._inject
                self._inject.clear()
        if out:
            os.write(fd, bytes(out))


def wall_room_mm(half_width_mm: float) -> Callable[[float], float]:
    """A square room centred on the device; angles clockwise from its 0° direction."""
    def d(angle_deg: float) -> float:
        a = math.radians(angle_deg)
        return half_width_mm / max(abs(math.cos(a)), abs(math.sin(a)))
    return d
