"""The motor base on a serial port: (v, ω) out as wheel speeds, encoder ticks back as odometry.

Layers of stopping, each enough on its own:

- the agent's watchdog sets (0, 0) when a command's time-to-live runs out or the server's
  liveliness disappears, and this driver sends STOP at once;
- this driver drops a target that was not renewed within ``hold_s`` (the agent loop hung);
- the firmware stops when no valid frame arrived for ``firmware_timeout_ms`` (this process or
  the cable died) and at once after a frame with a bad checksum;
- on any serial error (unreadable frame from the microcontroller, write or read failure, no
  encoder frames for ``link_timeout_s``) the driver sends STOP if it still can, drops the
  target, closes the port and reconnects every ``reconnect_s``. After reconnecting it sends
  STOP first, and the odometry continues from where it was (the microcontroller may have
  restarted its tick counters).

Odometry is stamped on the host clock (``time.time_ns``): each encoder frame carries the
microcontroller's milliseconds, and the offset between the two clocks is the smallest
(receive time − device time) over the last frames, which removes the serial latency's jitter.
"""

from __future__ import annotations

import bisect
import logging
import math
import termios  # pyserial's POSIX flush raises its error (EIO on an unplugged port)
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import serial

from robot_agent.backend import Odometry, Pose
from robot_agent.drivers import base_protocol as proto
from schemas.se2 import wrap_angle

log = logging.getLogger(__name__)


class BaseError(Exception):
    """The motor base cannot be used right now."""

    user_error = True


class BaseDisconnected(BaseError):
    """The serial port is missing or stopped working."""


class BaseTimeout(BaseError):
    """The microcontroller stopped sending encoder frames."""


class SerialBase:
    """A differential-drive base behind a microcontroller (the ``Base`` protocol)."""

    def __init__(self, port: str, track_m: float, wheel_radius_m: float, ticks_per_rev: float,
                 baud: int = 115200, keepalive_s: float = 0.05, hold_s: float = 0.4,
                 firmware_timeout_ms: int = 300, link_timeout_s: float = 0.5,
                 reconnect_s: float = 1.0, max_extrapolation_s: float = 0.3,
                 history: int = 500, serial_factory: Callable[..., Any] = serial.Serial) -> None:
        self.port, self.baud = port, baud
        self.track_m = track_m
        self.m_per_tick = 2 * math.pi * wheel_radius_m / ticks_per_rev
        self.keepalive_s, self.hold_s = keepalive_s, hold_s
        self.firmware_timeout_ms = firmware_timeout_ms
        self.link_timeout_s, self.reconnect_s = link_timeout_s, reconnect_s
        self.max_extrapolation_ns = int(max_extrapolation_s * 1e9)
        self.serial_factory = serial_factory
        self.counters: Counter[str] = Counter()
        self.connected = threading.Event()
        self.last_error = ""
        self._lock = threading.Lock()            # target, odometry
        self._io = threading.Lock()              # the port's writes
        self._serial: Any = None
        self._seq = 0
        self._target_tps = (0, 0)
        self._target_set = 0.0                   # monotonic time of the last set_velocity
        self._pose: Pose = (0.0, 0.0, 0.0)
        self._ticks: tuple[int, int] | None = None
        self._board_timed_out = False   # the last report said the board stopped on silence
        self._offsets: deque[int] = deque(maxlen=100)
        self._last_device_ms: int | None = None
        self._wraps = 0
        self._history: deque[Odometry] = deque(maxlen=history)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- the Base protocol ------------------------------------------------------------------
    def set_velocity(self, v_mps: float, omega_rps: float) -> None:
        left, right = proto.wheel_speeds(v_mps, omega_rps, self.track_m)
        tps = (round(left / self.m_per_tick), round(right / self.m_per_tick))
        with self._lock:
            self._target_tps = tps
            self._target_set = time.monotonic()
        self._send_target()

    def odometry_at(self, stamp_ns: int) -> Odometry | None:
        """Odometry interpolated at ``stamp_ns``; None outside the history (or too far ahead)."""
        with self._lock:
            h = list(self._history)
        if not h or stamp_ns < h[0].stamp_ns:
            return None
        if stamp_ns >= h[-1].stamp_ns:
            last = h[-1]
            dt_ns = stamp_ns - last.stamp_ns
            if dt_ns > self.max_extrapolation_ns:
                return None
            x, y, th = last.pose   # extrapolate a few ms with the last velocity
            dt = dt_ns * 1e-9
            return Odometry(stamp_ns, (x + last.v_mps * dt * math.cos(th),
                                       y + last.v_mps * dt * math.sin(th),
                                       wrap_angle(th + last.omega_rps * dt)),
                            last.v_mps, last.omega_rps)
        i = bisect.bisect_right([o.stamp_ns for o in h], stamp_ns)
        a, b = h[i - 1], h[i]
        s = (stamp_ns - a.stamp_ns) / max(b.stamp_ns - a.stamp_ns, 1)
        dth = wrap_angle(b.pose[2] - a.pose[2])
        return Odometry(stamp_ns, (a.pose[0] + s * (b.pose[0] - a.pose[0]),
                                   a.pose[1] + s * (b.pose[1] - a.pose[1]),
                                   wrap_angle(a.pose[2] + s * dth)),
                        a.v_mps + s * (b.v_mps - a.v_mps),
                        a.omega_rps + s * (b.omega_rps - a.omega_rps))

    # -- lifetime ---------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, daemon=True, name="motor-base")
        self._thread.start()

    def close(self) -> None:
        with self._lock:
            self._target_tps = (0, 0)
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._session()
            except (BaseError, proto.BaseProtocolError) as e:
                self.counters[f"base_{type(e).__name__}"] += 1
                if str(e) != self.last_error:
                    log.warning("motor base: %s; retrying every %g s", e, self.reconnect_s)
                    self.last_error = str(e)
            finally:
                self._disconnect()
            self._stop.wait(self.reconnect_s)

    def _session(self) -> None:
        try:
            port = self.serial_factory(self.port, self.baud, timeout=self.keepalive_s)
        except (serial.SerialException, OSError, termios.error) as e:
            raise BaseDisconnected(f"cannot open {self.port}: {e}") from None
        with self._lock:
            self._target_tps = (0, 0)        # never resume an old command after a reconnect
            self._ticks = None
            self._offsets.clear()
        with self._io:
            self._serial = port
        self._write(proto.stop_frame(self._next_seq()))
        parser = proto.FrameParser()
        last_frame = time.monotonic()
        next_keepalive = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_keepalive:
                self._expire_target(now)
                self._send_target()
                next_keepalive = now + self.keepalive_s
            try:
                data = port.read(max(port.in_waiting, 1))
            except (serial.SerialException, OSError, termios.error) as e:
                raise BaseDisconnected(f"{self.port}: read failed: {e}") from None
            recv_ns = time.time_ns()
            bad = parser.bad_frames
            for f in parser.feed(data):
                if f.kind == proto.ENCODERS:
                    self._on_encoders(proto.parse_encoders(f), recv_ns)
                    last_frame = time.monotonic()
                else:
                    self.counters["unknown_frames"] += 1
            if parser.bad_frames != bad:
                self.counters["bad_frames"] += parser.bad_frames - bad
                log.warning("motor base: frame with a bad checksum: stopping")
                with self._lock:
                    self._target_tps = (0, 0)
                self._send_target()
            if time.monotonic() - last_frame > self.link_timeout_s:
                raise BaseTimeout(f"{self.port}: no encoder frame for {self.link_timeout_s} s")
            if not self.connected.is_set() and self._ticks is not None:
                self.connected.set()
                self.counters["connects"] += 1
                if self.last_error:
                    log.info("motor base on %s back", self.port)
                    self.last_error = ""

    def _disconnect(self) -> None:
        self.connected.clear()
        with self._lock:
            self._target_tps = (0, 0)
        with self._io:
            port, self._serial = self._serial, None
        if port is None:
            return
        try:  # best effort: the port may be gone
            port.write(proto.stop_frame(self._next_seq()))
            port.flush()
        except (serial.SerialException, OSError, termios.error):
            pass
        try:
            port.close()
        except (serial.SerialException, OSError, termios.error) as e:
            log.debug("closing %s: %s", self.port, e)

    # -- frames -----------------------------------------------------------------------------
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _write(self, data: bytes) -> None:
        with self._io:
            if self._serial is None:
                return
            try:
                self._serial.write(data)
                self._serial.flush()
            except (serial.SerialException, OSError, termios.error) as e:
                self.counters["write_errors"] += 1
                raise BaseDisconnected(f"{self.port}: write failed: {e}") from None

    def _send_target(self) -> None:
        with self._lock:
            left, right = self._target_tps
        if left == 0 and right == 0:
            data = proto.stop_frame(self._next_seq())
        else:
            data = proto.speed_frame(self._next_seq(), left, right, self.firmware_timeout_ms)
        try:
            self._write(data)
        except BaseDisconnected as e:
            if threading.current_thread() is self._thread:
                raise
            log.debug("command not sent: %s", e)   # the driver's thread reconnects

    def _expire_target(self, now: float) -> None:
        with self._lock:
            if self._target_tps != (0, 0) and now - self._target_set > self.hold_s:
                self._target_tps = (0, 0)
                self.counters["hold_expired"] += 1
                log.info("no velocity command for %g s: stopping", self.hold_s)

    def _on_encoders(self, e: proto.Encoders, recv_ns: int) -> None:
        # the board's own verdicts first: every report counts, whatever its time and ticks
        if e.flags & proto.FLAG_BAD_FRAME:
            self.counters["firmware_bad_frames"] += 1
        timed_out = bool(e.flags & proto.FLAG_TIMEOUT)
        if timed_out and not self._board_timed_out:
            self.counters["firmware_timeouts"] += 1   # the board stopped on silence
        self._board_timed_out = timed_out
        with self._lock:
            if self._last_device_ms is not None and e.time_ms < self._last_device_ms:
                if self._last_device_ms - e.time_ms < 2**31:
                    self._offsets.clear()    # the microcontroller restarted
                    self._ticks = None
                else:
                    self._wraps += 1         # its uint32 milliseconds wrapped (49.7 days)
            self._last_device_ms = e.time_ms
            device_ns = (e.time_ms + self._wraps * 2**32) * 1_000_000
            self._offsets.append(recv_ns - device_ns)
            stamp = device_ns + min(self._offsets)
            if self._ticks is None:
                self._ticks = (e.left_ticks, e.right_ticks)
                self._history.append(Odometry(stamp, self._pose))
                return
            dl = proto.tick_delta(e.left_ticks, self._ticks[0]) * self.m_per_tick
            dr = proto.tick_delta(e.right_ticks, self._ticks[1]) * self.m_per_tick
            self._ticks = (e.left_ticks, e.right_ticks)
            self._pose = proto.integrate(self._pose, dl, dr, self.track_m)
            prev = self._history[-1] if self._history else None
            if prev is not None and stamp <= prev.stamp_ns:
                return
            dt = (stamp - prev.stamp_ns) * 1e-9 if prev is not None else 0.0
            v = 0.5 * (dl + dr) / dt if dt > 0 else 0.0
            w = (dr - dl) / self.track_m / dt if dt > 0 else 0.0
            self._history.append(Odometry(stamp, self._pose, v, w))
