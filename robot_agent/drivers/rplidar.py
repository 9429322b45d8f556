"""RPLIDAR A-series over a serial port (pyserial): requests, scanning, unplugging, reconnecting.

``Rplidar`` speaks the protocol on one open port and raises typed errors: ``LidarDisconnected``
when the port cannot be opened or stops working (the USB cable came out), ``LidarTimeout`` when
the device does not answer, ``LidarHealthError`` when it reports a fault. ``RplidarSource`` is
the agent's ``LidarSource``: a thread that connects, checks health, spins the motor up, scans,
hands each revolution on as a fixed-beam ``Sweep`` and, on any of those errors, closes the port
and tries again every ``reconnect_s`` (a udev symlink such as ``/dev/rplidar`` keeps the name
stable across replugging).

Motor: on the A2's USB adapter the motor enable follows the DTR line; DTR low (pyserial
``dtr = False``) runs the motor, DTR high stops it.
"""

from __future__ import annotations

import errno
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import serial

from robot_agent.backend import Sweep
from robot_agent.drivers import rplidar_protocol as proto

log = logging.getLogger(__name__)


class LidarError(Exception):
    """The LIDAR cannot be used right now."""

    user_error = True


class LidarDisconnected(LidarError):
    """The serial port is missing or stopped working (device unplugged)."""


class LidarTimeout(LidarError):
    """The device did not answer or stopped streaming."""


class LidarHealthError(LidarError):
    """The device reports an error state."""


class Rplidar:
    """One RPLIDAR on an open serial port."""

    def __init__(self, port: str, baud: int = 115200, timeout_s: float = 1.0,
                 motor_dtr: bool = True,
                 serial_factory: Callable[..., Any] = serial.Serial) -> None:
        self.port, self.baud, self.timeout_s, self.motor_dtr = port, baud, timeout_s, motor_dtr
        try:
            self._serial = serial_factory(port, baud, timeout=0.05)
        except (serial.SerialException, OSError) as e:
            raise LidarDisconnected(f"cannot open {port}: {e}") from None
        self.parser = proto.NodeParser()
        self.motor_control_failed = False

    def close(self) -> None:
        try:
            self._serial.close()
        except (serial.SerialException, OSError) as e:
            log.debug("closing %s: %s", self.port, e)

    # -- bytes ------------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        try:
            self._serial.write(data)
            self._serial.flush()
        except (serial.SerialException, OSError) as e:
            raise LidarDisconnected(f"{self.port}: write failed: {e}") from None

    def read_available(self) -> bytes:
        """Whatever arrived (waits up to the port's short timeout for the first byte)."""
        try:
            return bytes(self._serial.read(max(self._serial.in_waiting, 1)))
        except (serial.SerialException, OSError) as e:
            raise LidarDisconnected(f"{self.port}: read failed: {e}") from None

    def _read_exact(self, n: int) -> bytes:
        out = bytearray()
        deadline = time.monotonic() + self.timeout_s
        while len(out) < n:
            if time.monotonic() > deadline:
                raise LidarTimeout(f"{self.port}: {len(out)} of {n} bytes within "
                                   f"{self.timeout_s} s")
            try:
                out += self._serial.read(n - len(out))
            except (serial.SerialException, OSError) as e:
                raise LidarDisconnected(f"{self.port}: read failed: {e}") from None
        return bytes(out)

    def _descriptor(self, data_type: int, mode: int, length: int | None) -> proto.Descriptor:
        """Wait for ``A5 5A`` (skipping stray bytes, e.g. the tail of a stopped scan)."""
        deadline = time.monotonic() + self.timeout_s
        prev = -1
        while True:
            b = self._read_exact(1)[0]
            if prev == proto.SYNC and b == proto.SYNC2:
                break
            prev = b
            if time.monotonic() > deadline:
                raise LidarTimeout(f"{self.port}: no response descriptor within "
                                   f"{self.timeout_s} s")
        d = proto.parse_descriptor(bytes((proto.SYNC, proto.SYNC2)) + self._read_exact(5))
        if d.data_type != data_type or d.mode != mode or (length is not None
                                                           and d.length != length):
            raise proto.RplidarProtocolError(
                f"expected response type {data_type:#04x} mode {mode} length {length}, got "
                f"type {d.data_type:#04x} mode {d.mode} length {d.length}")
        return d

    # -- requests ---------------------------------------------------------------------------
    def stop(self) -> None:
        """Stop scanning and drop what was in flight (the device needs ~1 ms)."""
        self._write(proto.request(proto.CMD_STOP))
        time.sleep(0.01)
        try:
            self._serial.reset_input_buffer()
        except (serial.SerialException, OSError) as e:
            raise LidarDisconnected(f"{self.port}: {e}") from None
        self.parser.reset()

    def reset(self) -> None:
        """Restart the device's core (it prints a banner, then is ready after ~2 ms)."""
        self._write(proto.request(proto.CMD_RESET))
        time.sleep(0.05)
        try:
            self._serial.reset_input_buffer()
        except (serial.SerialException, OSError) as e:
            raise LidarDisconnected(f"{self.port}: {e}") from None

    def info(self) -> proto.DeviceInfo:
        self._write(proto.request(proto.CMD_GET_INFO))
        self._descriptor(proto.TYPE_INFO, proto.MODE_SINGLE, proto.INFO_LEN)
        return proto.parse_info(self._read_exact(proto.INFO_LEN))

    def health(self) -> proto.Health:
        self._write(proto.request(proto.CMD_GET_HEALTH))
        self._descriptor(proto.TYPE_HEALTH, proto.MODE_SINGLE, proto.HEALTH_LEN)
        return proto.parse_health(self._read_exact(proto.HEALTH_LEN))

    def motor(self, on: bool) -> None:
        if not self.motor_dtr:
            return
        try:
            self._serial.dtr = not on
        except (serial.SerialException, OSError) as e:
            # a port without modem lines (a pseudo-terminal, some adapters) cannot do this
            if getattr(e, "errno", None) in (errno.ENOTTY, errno.EINVAL):
                self.motor_control_failed = True
                return
            raise LidarDisconnected(f"{self.port}: motor control failed: {e}") from None

    def start_scan(self) -> None:
        self._write(proto.request(proto.CMD_SCAN))
        self._descriptor(proto.TYPE_SCAN, proto.MODE_MULTIPLE, proto.NODE_LEN)
        self.parser.reset()

    def nodes(self, stall_s: float = 2.0, stop: threading.Event | None = None
              ) -> Iterator[tuple[proto.Nodes, int]]:
        """Scan nodes as they arrive, with the arrival time [ns, time.time_ns], until ``stop``."""
        last = time.monotonic()
        while stop is None or not stop.is_set():
            data = self.read_available()
            now = time.monotonic()
            if not data:
                if now - last > stall_s:
                    raise LidarTimeout(f"{self.port}: no scan data for {stall_s} s")
                continue
            nodes = self.parser.feed(data)
            if len(nodes):
                last = now
                yield nodes, time.time_ns()


class RplidarSource:
    """The agent's LIDAR: revolutions from an RPLIDAR as fixed-beam sweeps, reconnecting."""

    def __init__(self, port: str, baud: int = 115200, beams: int = 360,
                 range_min_mm: int = 150, range_max_mm: int = 12000, mount_yaw_rad: float = 0.0,
                 clockwise: bool = True, motor_dtr: bool = True, reconnect_s: float = 1.0,
                 timeout_s: float = 1.0, stall_s: float = 2.0,
                 serial_factory: Callable[..., Any] = serial.Serial) -> None:
        self.port, self.baud = port, baud
        self.beams, self.range_min_mm, self.range_max_mm = beams, range_min_mm, range_max_mm
        self.mount_yaw_rad, self.clockwise, self.motor_dtr = mount_yaw_rad, clockwise, motor_dtr
        self.reconnect_s, self.timeout_s, self.stall_s = reconnect_s, timeout_s, stall_s
        self.serial_factory = serial_factory
        self.counters: Counter[str] = Counter()
        self.info: proto.DeviceInfo | None = None
        self.connected = threading.Event()
        self._stop = threading.Event()
        self._device: Rplidar | None = None
        self._thread: threading.Thread | None = None
        self.last_error = ""

    def start(self, on_sweep: Callable[[Sweep], None]) -> None:
        self._thread = threading.Thread(target=self._run, args=(on_sweep,), daemon=True,
                                        name="rplidar")
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)

    def _run(self, on_sweep: Callable[[Sweep], None]) -> None:
        while not self._stop.is_set():
            try:
                self._session(on_sweep)
            except (LidarError, proto.RplidarProtocolError) as e:
                self.counters[f"lidar_{type(e).__name__}"] += 1
                if str(e) != self.last_error:  # log each new problem once, not every retry
                    log.warning("LIDAR: %s; retrying every %g s", e, self.reconnect_s)
                    self.last_error = str(e)
            finally:
                self.connected.clear()
                self._shutdown_device()
            self._stop.wait(self.reconnect_s)

    def _session(self, on_sweep: Callable[[Sweep], None]) -> None:
        dev = self._device = Rplidar(self.port, self.baud, self.timeout_s, self.motor_dtr,
                                     self.serial_factory)
        dev.stop()
        self.info = dev.info()
        health = dev.health()
        if health.status == "error":
            log.warning("LIDAR reports error %#06x: resetting", health.error_code)
            dev.reset()
            health = dev.health()
            if health.status == "error":
                raise LidarHealthError(f"{self.port}: device error {health.error_code:#06x} "
                                       "persists after a reset")
        dev.motor(True)
        if dev.motor_control_failed:
            self.counters["motor_control_unsupported"] += 1
        dev.start_scan()
        self.connected.set()
        self.counters["connects"] += 1
        if self.last_error:
            log.info("LIDAR on %s back (model %d, firmware %d.%02d)", self.port,
                     self.info.model, *self.info.firmware)
            self.last_error = ""
        assembler = proto.RevolutionAssembler()
        skipped = 0
        for nodes, stamp_ns in dev.nodes(self.stall_s, self._stop):
            if dev.parser.skipped_bytes != skipped:
                self.counters["corrupt_bytes"] += dev.parser.skipped_bytes - skipped
                skipped = dev.parser.skipped_bytes
            for rev in assembler.feed(nodes, stamp_ns):
                on_sweep(proto.to_sweep(rev, self.beams, self.range_min_mm, self.range_max_mm,
                                        self.mount_yaw_rad, self.clockwise))
                self.counters["sweeps"] += 1
            self.counters["short_revolutions"] = assembler.short_revolutions

    def _shutdown_device(self) -> None:
        dev, self._device = self._device, None
        if dev is None:
            return
        try:  # best effort: the device may be gone
            dev.stop()
            dev.motor(False)
        except LidarError:
            pass
        dev.close()
