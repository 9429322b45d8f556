"""The SLAMTEC RPLIDAR A-series serial protocol (standard scan mode), bytes only.

Requests are ``0xA5 CMD`` (commands ≥ 0x80 add ``size payload checksum``, the checksum being
the XOR of every byte before it). Answers start with a 7-byte response descriptor
``0xA5 0x5A`` + a little-endian 32-bit word (low 30 bits: length of one response, high 2 bits:
send mode, 0 = single, 1 = multiple) + the data type. A running SCAN streams 5-byte nodes:

    byte 0   bit 0 S (first node of a new 360° revolution), bit 1 !S, bits 2-7 quality
    byte 1   bit 0 C (check bit, always 1), bits 1-7 angle_q6 bits 0-6
    byte 2   angle_q6 bits 7-14             angle = angle_q6 / 64 [deg], clockwise from above
    byte 3-4 distance_q2 (little-endian)    distance = distance_q2 / 4 [mm], 0 = no return

``NodeParser`` cuts a byte stream into nodes and resynchronises after corrupted bytes;
``RevolutionAssembler`` groups nodes into revolutions at the start flag; ``to_sweep`` turns a
revolution into the fixed-beam ``Sweep`` the server's ``Scan`` message needs.
"""

from __future__ import annotations

import itertools
import math
import struct
from dataclasses import dataclass

import numpy as np

from robot_agent.backend import Sweep
from robot_agent.drivers.beams import to_beams
from schemas.se2 import wrap_angle

SYNC = 0xA5
SYNC2 = 0x5A
CMD_STOP = 0x25
CMD_RESET = 0x40
CMD_SCAN = 0x20
CMD_GET_INFO = 0x50
CMD_GET_HEALTH = 0x52
CMD_SET_MOTOR_PWM = 0xF0       # A2/A3 with accessory board; the USB adapter uses DTR instead

TYPE_INFO = 0x04
TYPE_HEALTH = 0x06
TYPE_SCAN = 0x81
MODE_SINGLE = 0
MODE_MULTIPLE = 1

DESCRIPTOR_LEN = 7
INFO_LEN = 20
HEALTH_LEN = 3
NODE_LEN = 5
HEALTH_STATUS = {0: "good", 1: "warning", 2: "error"}
#: nodes after a corrupted byte that must all be valid before the stream counts as aligned
RESYNC_NODES = 3


class RplidarProtocolError(ValueError):
    """Bytes from the device that do not follow the protocol."""

    user_error = True


def request(cmd: int, payload: bytes = b"") -> bytes:
    """The bytes of one request; commands with a payload carry its size and an XOR checksum."""
    if not payload:
        return bytes((SYNC, cmd))
    head = bytes((SYNC, cmd, len(payload))) + payload
    checksum = 0
    for b in head:
        checksum ^= b
    return head + bytes((checksum,))


@dataclass(frozen=True)
class Descriptor:
    length: int
    mode: int
    data_type: int

    def encode(self) -> bytes:
        return bytes((SYNC, SYNC2)) + struct.pack("<IB", (self.length & 0x3FFFFFFF)
                                                  | (self.mode << 30), self.data_type)


def parse_descriptor(raw: bytes) -> Descriptor:
    if len(raw) != DESCRIPTOR_LEN or raw[0] != SYNC or raw[1] != SYNC2:
        raise RplidarProtocolError(f"bad response descriptor {raw.hex(' ')}")
    word, data_type = struct.unpack("<IB", raw[2:])
    return Descriptor(word & 0x3FFFFFFF, word >> 30, data_type)


@dataclass(frozen=True)
class DeviceInfo:
    model: int
    firmware: tuple[int, int]        # (major, minor)
    hardware: int
    serial_number: str               # 32 hex digits

    def encode(self) -> bytes:
        return bytes((self.model, self.firmware[1], self.firmware[0], self.hardware)) \
            + bytes.fromhex(self.serial_number)


def parse_info(raw: bytes) -> DeviceInfo:
    if len(raw) != INFO_LEN:
        raise RplidarProtocolError(f"device info of {len(raw)} bytes, expected {INFO_LEN}")
    return DeviceInfo(raw[0], (raw[2], raw[1]), raw[3], raw[4:].hex().upper())


@dataclass(frozen=True)
class Health:
    status: str                      # good, warning, error
    error_code: int


def parse_health(raw: bytes) -> Health:
    if len(raw) != HEALTH_LEN:
        raise RplidarProtocolError(f"health of {len(raw)} bytes, expected {HEALTH_LEN}")
    status, code = struct.unpack("<BH", raw)
    if status not in HEALTH_STATUS:
        raise RplidarProtocolError(f"health status {status} is not 0, 1 or 2")
    return Health(HEALTH_STATUS[status], code)


def encode_node(start: bool, quality: int, angle_deg: float, distance_mm: float) -> bytes:
    """One standard scan node, as the device sends it."""
    angle_q6 = round(angle_deg * 64.0) % (360 * 64)
    dist_q2 = min(max(round(distance_mm * 4.0), 0), 0xFFFF)
    b0 = (int(start) | (int(not start) << 1) | ((quality & 0x3F) << 2))
    return bytes((b0, ((angle_q6 & 0x7F) << 1) | 1, angle_q6 >> 7, dist_q2 & 0xFF, dist_q2 >> 8))


@dataclass(frozen=True)
class Nodes:
    """Decoded nodes: start flags, quality 0..63, angle [deg clockwise], distance [mm]."""

    start: np.ndarray
    quality: np.ndarray
    angle_deg: np.ndarray
    distance_mm: np.ndarray

    def __len__(self) -> int:
        return len(self.start)


def _valid(groups: np.ndarray) -> np.ndarray:
    """Which (N, 5) byte groups are well-formed nodes: S != !S, C = 1, angle < 360°."""
    b0, b1 = groups[:, 0], groups[:, 1]
    angle_q6 = (b1.astype(np.int32) >> 1) | (groups[:, 2].astype(np.int32) << 7)
    return (((b0 ^ (b0 >> 1)) & 1) == 1) & ((b1 & 1) == 1) & (angle_q6 < 360 * 64)


def decode_nodes(groups: np.ndarray) -> Nodes:
    g = groups.astype(np.int32)
    return Nodes(start=(g[:, 0] & 1) == 1, quality=g[:, 0] >> 2,
                 angle_deg=((g[:, 1] >> 1) | (g[:, 2] << 7)) / 64.0,
                 distance_mm=(g[:, 3] | (g[:, 4] << 8)) / 4.0)


class NodeParser:
    """Cuts the scan byte stream into nodes; skips bytes until nodes are well-formed again.

    A random byte pattern passes the node checks about one time in five, so after a bad group
    the parser only trusts an alignment once ``RESYNC_NODES`` consecutive groups are valid.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._aligned = True
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> Nodes:
        self._buf += data
        out: list[np.ndarray] = []
        while len(self._buf) >= NODE_LEN:
            n = len(self._buf) // NODE_LEN
            groups = np.frombuffer(bytes(self._buf[:n * NODE_LEN]), np.uint8).reshape(n, 5)
            ok = _valid(groups)
            if not self._aligned:
                if n < RESYNC_NODES:
                    break  # wait for more bytes to judge this alignment
                if ok[:RESYNC_NODES].all():
                    self._aligned = True
                else:
                    del self._buf[0]
                    self.skipped_bytes += 1
                    continue
            bad = np.flatnonzero(~ok)
            k = int(bad[0]) if len(bad) else n
            if k:
                out.append(groups[:k])
            if k == n:
                del self._buf[:n * NODE_LEN]
                break
            del self._buf[:k * NODE_LEN + 1]
            self.skipped_bytes += 1
            self._aligned = False
        if not out:
            return decode_nodes(np.zeros((0, 5), np.uint8))
        return decode_nodes(np.concatenate(out))

    def reset(self) -> None:
        self._buf.clear()
        self._aligned = True


@dataclass(frozen=True)
class Revolution:
    """The nodes of one 360° turn, as measured (device angles, clockwise)."""

    stamp_ns: int                    # middle of the turn
    angle_deg: np.ndarray
    distance_mm: np.ndarray
    quality: np.ndarray


class RevolutionAssembler:
    """Groups nodes into revolutions: a node with the start flag closes the running one.

    Nodes before the first start flag belong to a partial turn and are dropped. Each node is
    stamped by linear interpolation between the arrival times of the batches around it, which
    the revolution's stamp (the middle of its first and last node) inherits.
    """

    def __init__(self, min_nodes: int = 16) -> None:
        self.min_nodes = min_nodes
        self._parts: list[tuple[Nodes, int, int]] = []   # nodes, first and last stamp
        self._started = False
        self._last_stamp: int | None = None
        self.short_revolutions = 0

    def feed(self, nodes: Nodes, stamp_ns: int) -> list[Revolution]:
        if not len(nodes):
            return []
        t0 = self._last_stamp if self._last_stamp is not None else stamp_ns
        self._last_stamp = stamp_ns
        stamps = np.linspace(t0, stamp_ns, len(nodes) + 1)[1:].astype(np.int64)
        out: list[Revolution] = []
        edges = sorted({0, *(int(i) for i in np.flatnonzero(nodes.start)), len(nodes)})
        for a, b in itertools.pairwise(edges):
            if nodes.start[a]:
                rev = self._close()
                if rev is not None:
                    out.append(rev)
                self._started = True
            if self._started:
                part = Nodes(nodes.start[a:b], nodes.quality[a:b], nodes.angle_deg[a:b],
                             nodes.distance_mm[a:b])
                self._parts.append((part, int(stamps[a]), int(stamps[b - 1])))
        return out

    def _close(self) -> Revolution | None:
        parts, self._parts = self._parts, []
        if not parts:
            return None
        n = sum(len(p) for p, _, _ in parts)
        if n < self.min_nodes:
            self.short_revolutions += 1
            return None
        return Revolution(stamp_ns=(parts[0][1] + parts[-1][2]) // 2,
                          angle_deg=np.concatenate([p.angle_deg for p, _, _ in parts]),
                          distance_mm=np.concatenate([p.distance_mm for p, _, _ in parts]),
                          quality=np.concatenate([p.quality for p, _, _ in parts]))

    def reset(self) -> None:
        self._parts, self._started, self._last_stamp = [], False, None


def robot_angles_rad(angle_deg: np.ndarray, mount_yaw_rad: float = 0.0,
                     clockwise: bool = True) -> np.ndarray:
    """Device angles [deg] -> robot-frame angles [rad], counter-clockwise, wrapped to (−π, π].

    The RPLIDAR measures clockwise seen from above; the robot frame turns counter-clockwise.
    ``mount_yaw_rad`` is the yaw of the device's 0° direction in the robot frame.
    """
    a = np.radians(angle_deg)
    a = mount_yaw_rad + (-a if clockwise else a)
    return wrap_angle(np.asarray(a))


def to_sweep(rev: Revolution, beams: int, range_min_mm: int, range_max_mm: int,
             mount_yaw_rad: float = 0.0, clockwise: bool = True) -> Sweep:
    """Resample one revolution onto ``beams`` fixed beams from −π, counter-clockwise.

    ``beams.to_beams`` places the measurements: at the nearest beam, a lone beam left empty by
    rounding taking one from a neighbour that got two, the nearest obstacle winning where
    several share a beam (the conservative reading for mapping and collision avoidance). Beams
    without a measurement, and distances of 0 or outside ``[range_min_mm, range_max_mm]``, are
    no-returns (0 mm).
    """
    theta = robot_angles_rad(rev.angle_deg, mount_yaw_rad, clockwise)
    mm = np.rint(rev.distance_mm)
    ok = (mm >= max(range_min_mm, 1)) & (mm <= range_max_mm)
    ranges = to_beams(theta, np.where(ok, mm, np.inf), beams)
    return Sweep(stamp_ns=rev.stamp_ns, angle_min_rad=-math.pi,
                 angle_increment_rad=2 * math.pi / beams, range_min_mm=range_min_mm,
                 range_max_mm=range_max_mm,
                 ranges_mm=np.where(np.isfinite(ranges), ranges, 0).astype("<u2").tobytes())
