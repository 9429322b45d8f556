"""The motor base: differential-drive kinematics and the serial frames to its microcontroller.

Frames (both directions, documented with the firmware in deploy/firmware/README.md)::

    0xAA 0x55 | type | seq | len | payload (len bytes, little-endian) | crc8

``crc8`` is CRC-8 (polynomial 0x07, initial value 0) over ``type seq len payload``.

    SPEED     0x01 host -> MCU  int32 left, int32 right [encoder ticks/s], uint16 timeout [ms]
    STOP      0x02 host -> MCU  (empty)
    ENCODERS  0x81 MCU -> host  uint32 time [ms], int32 left, int32 right [ticks, cumulative],
                                uint8 flags (bit 0 stopped by timeout, bit 1 stopped after a
                                bad frame, bit 2 motors driven)

The firmware holds a SPEED for its ``timeout`` and stops the motors when no valid frame comes,
and at once after a frame with a bad checksum.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from schemas.se2 import wrap_angle

PREAMBLE = b"\xaa\x55"
SPEED = 0x01
STOP = 0x02
ENCODERS = 0x81
MAX_PAYLOAD = 32
FLAG_TIMEOUT, FLAG_BAD_FRAME, FLAG_DRIVING = 1, 2, 4
_SPEED = struct.Struct("<iiH")
_ENCODERS = struct.Struct("<IiiB")


class BaseProtocolError(ValueError):
    """A frame from the microcontroller that cannot be used."""

    user_error = True


def crc8(data: bytes) -> int:
    """CRC-8, polynomial x⁸ + x² + x + 1 (0x07), initial value 0, no reflection."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def frame(kind: int, seq: int, payload: bytes = b"") -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise BaseProtocolError(f"payload of {len(payload)} bytes, at most {MAX_PAYLOAD}")
    body = bytes((kind, seq & 0xFF, len(payload))) + payload
    return PREAMBLE + body + bytes((crc8(body),))


def speed_frame(seq: int, left_tps: int, right_tps: int, timeout_ms: int) -> bytes:
    return frame(SPEED, seq, _SPEED.pack(left_tps, right_tps, timeout_ms))


def stop_frame(seq: int) -> bytes:
    return frame(STOP, seq)


@dataclass(frozen=True)
class Encoders:
    time_ms: int
    left_ticks: int
    right_ticks: int
    flags: int

    def encode(self, seq: int) -> bytes:
        return frame(ENCODERS, seq, _ENCODERS.pack(self.time_ms & 0xFFFFFFFF, self.left_ticks,
                                                   self.right_ticks, self.flags))


@dataclass(frozen=True)
class Frame:
    kind: int
    seq: int
    payload: bytes


def parse_encoders(f: Frame) -> Encoders:
    if f.kind != ENCODERS or len(f.payload) != _ENCODERS.size:
        raise BaseProtocolError(f"frame type {f.kind:#04x} with {len(f.payload)} bytes is not "
                                f"an ENCODERS frame ({_ENCODERS.size} bytes)")
    return Encoders(*_ENCODERS.unpack(f.payload))


def parse_speed(f: Frame) -> tuple[int, int, int]:
    if f.kind != SPEED or len(f.payload) != _SPEED.size:
        raise BaseProtocolError(f"frame type {f.kind:#04x} is not a SPEED frame")
    left, right, timeout_ms = _SPEED.unpack(f.payload)
    return left, right, timeout_ms


class FrameParser:
    """Frames out of a byte stream; bytes that do not start a valid frame are skipped."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_frames = 0
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> list[Frame]:
        self._buf += data
        out: list[Frame] = []
        buf = self._buf
        while True:
            start = buf.find(PREAMBLE)
            if start < 0:
                keep = 1 if buf.endswith(PREAMBLE[:1]) else 0
                self.skipped_bytes += len(buf) - keep
                del buf[:len(buf) - keep]
                return out
            if start:
                self.skipped_bytes += start
                del buf[:start]
            if len(buf) < 5:
                return out
            n = buf[4]
            if n > MAX_PAYLOAD:
                self._reject()
                continue
            if len(buf) < 6 + n:
                return out
            body = bytes(buf[2:5 + n])
            if crc8(body) != buf[5 + n]:
                self._reject()
                continue
            out.append(Frame(body[0], body[1], body[3:]))
            del buf[:6 + n]

    def _reject(self) -> None:
        self.bad_frames += 1
        self.skipped_bytes += 1
        del self._buf[0]


def wheel_speeds(v_mps: float, omega_rps: float, track_m: float) -> tuple[float, float]:
    """Differential drive: (v_left, v_right) [m/s] = (v − ω·b/2, v + ω·b/2), b the track."""
    half = 0.5 * omega_rps * track_m
    return v_mps - half, v_mps + half


def integrate(pose: tuple[float, float, float], d_left_m: float, d_right_m: float,
              track_m: float) -> tuple[float, float, float]:
    """Advance a pose by wheel travel: ds = (dl + dr)/2, dθ = (dr − dl)/b, along the arc."""
    x, y, th = pose
    ds = 0.5 * (d_left_m + d_right_m)
    dth = (d_right_m - d_left_m) / track_m
    # chord of the arc: exact for constant wheel speeds within the step
    chord = ds if abs(dth) < 1e-9 else 2.0 * ds / dth * math.sin(0.5 * dth)
    x += chord * math.cos(th + 0.5 * dth)
    y += chord * math.sin(th + 0.5 * dth)
    return x, y, wrap_angle(th + dth)


def tick_delta(new: int, old: int) -> int:
    """Difference of two int32 tick counters, across wrap-around."""
    return ((new - old + 2**31) % 2**32) - 2**31
