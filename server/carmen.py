"""Reader for CARMEN laser logs (``.clf``/``.log``, optionally ``.gz``/``.bz2``).

One message per line, the last three words being ``ipc_timestamp ipc_hostname
logger_timestamp``. Laser lines understood here:

- ``FLASER``/``RLASER n r_1..r_n x y θ odom_x odom_y odom_θ`` (front/rear laser with the laser
  pose and the robot pose from odometry);
- ``ROBOTLASER1``/``ROBOTLASER2 type start fov resolution max_range accuracy remission_mode
  n r_1..r_n m e_1..e_m laser_x laser_y laser_θ robot_x robot_y robot_θ tv rv fsd ssd turn_axis``;
- ``RAWLASER1..4 type start fov resolution max_range accuracy remission_mode n r.. m e..`` and
  the old ``LASER1..4 n r..`` (no pose: odometry comes from ``ODOM`` lines);
- ``ODOM x y θ tv rv accel``.

Old-format lines do not carry the beam geometry; as CARMEN itself does, it is guessed from the
number of beams: start −π/2, 1° steps for 180/181 beams, 0.5° for 360/361, 0.25° for 400/401,
otherwise a 180° field of view. Lines that are truncated or corrupt are skipped and counted.
"""

from __future__ import annotations

import bz2
import functools
import gzip
import io
import logging
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
FRONT_KINDS = ("ROBOTLASER1", "FLASER", "RAWLASER1", "LASER1")
REAR_KINDS = ("ROBOTLASER2", "RLASER", "RAWLASER2", "LASER2")
IGNORED_KINDS = frozenset({"PARAM", "SYNC", "TRUEPOS", "NMEAGGA", "NMEARMC", "NMEA-GGA",
                           "SONAR", "BUMPER", "IMU", "ARM", "POSITIONLASER", "GPSNMEA"})
MAX_ERROR_EXAMPLES = 5


class CarmenError(Exception):
    """The log cannot be read at all (missing, unreadable, or without laser scans)."""

    user_error = True


class LineError(ValueError):
    """One line is corrupt or truncated; the reader skips and counts it."""


@dataclass(frozen=True, slots=True)
class LaserRecord:
    """One laser scan. ``laser_pose``/``robot_pose`` are odometry-frame (x, y, θ) or None."""

    kind: str
    stamp_text: str
    stamp_s: float
    ranges_m: F64
    angles_rad: F64
    max_range_m: float | None
    laser_pose: F64 | None
    robot_pose: F64 | None
    line_no: int


@dataclass(frozen=True, slots=True)
class OdometryRecord:
    stamp_text: str
    stamp_s: float
    pose: F64
    line_no: int


@dataclass
class ReadStats:
    """What the reader saw: lines per message type and lines skipped, by reason."""

    lines: int = 0
    by_kind: Counter[str] = field(default_factory=Counter)
    skipped: Counter[str] = field(default_factory=Counter)
    examples: list[str] = field(default_factory=list)
    truncated_stream: bool = False

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())

    def skip(self, reason: str, line_no: int, detail: str) -> None:
        self.skipped[reason] += 1
        if len(self.examples) < MAX_ERROR_EXAMPLES:
            self.examples.append(f"line {line_no}: {detail}")


@functools.lru_cache(maxsize=16)
def guess_beam_angles(n_beams: int) -> F64:
    """Beam angles [rad] of an old-format scan of ``n_beams`` beams (CARMEN's convention).
    The array is shared between scans: read-only."""
    if n_beams in (180, 181):
        step = math.pi / 180.0
    elif n_beams in (360, 361):
        step = math.pi / 360.0
    elif n_beams in (400, 401):
        step = math.pi / 720.0
    else:
        step = math.pi / max(n_beams - 1, 1)
    angles = -math.pi / 2.0 + step * np.arange(n_beams, dtype=np.float64)
    angles.flags.writeable = False
    return angles


def open_text(path: Path) -> IO[str]:
    """Open a possibly compressed log as text; undecodable bytes become U+FFFD (then fail)."""
    suffix = path.suffix.lower()
    raw: IO[bytes]
    # the streams are returned to the caller, who closes them
    if suffix == ".gz":
        raw = gzip.open(path, "rb")  # type: ignore[assignment]  # noqa: SIM115
    elif suffix == ".bz2":
        raw = bz2.open(path, "rb")  # noqa: SIM115
    else:
        raw = open(path, "rb")  # noqa: SIM115
    return io.TextIOWrapper(raw, encoding="ascii", errors="replace")


def _floats(words: list[str], start: int, stop: int) -> F64:
    if stop > len(words):
        raise LineError(f"truncated: expected at least {stop} fields, got {len(words)}")
    try:
        return np.asarray(words[start:stop], dtype=np.float64)
    except ValueError:
        raise LineError("non-numeric field") from None


def _count(words: list[str], i: int, allow_zero: bool = False) -> int:
    if i >= len(words):
        raise LineError("truncated before the number of readings")
    try:
        n = int(words[i])
    except ValueError:
        raise LineError(f"bad reading count {words[i]!r}") from None
    if not (0 if allow_zero else 1) <= n <= 100_000:
        raise LineError(f"implausible reading count {n}")
    return n


def _tail(words: list[str], i: int, line_no: int) -> tuple[str, float]:
    """The ipc timestamp (text and value) from the three words after index ``i``."""
    if len(words) != i + 3:
        raise LineError(f"expected {i + 3} fields, got {len(words)}")
    text = words[i]
    try:
        value = float(text)
    except ValueError:
        raise LineError(f"bad timestamp {text!r}") from None
    if not math.isfinite(value):
        raise LineError(f"non-finite timestamp {text!r}")
    return text, value


def _pose(values: F64) -> F64:
    if not np.isfinite(values).all():
        raise LineError("non-finite pose")
    return values


def _pose_words(words: list[str], start: int) -> F64:
    """Three finite numbers from ``words[start:start + 3]``."""
    try:
        x, y, t = float(words[start]), float(words[start + 1]), float(words[start + 2])
    except (ValueError, IndexError):
        raise LineError("bad pose fields") from None
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(t)):
        raise LineError("non-finite pose")
    return np.array([x, y, t])


def parse_line(line: str, line_no: int) -> LaserRecord | OdometryRecord | str | None:
    """Parse one line: a record, the message kind (str) if ignored, or None if blank/comment.

    Raises LineError for a corrupt or truncated line.
    """
    words = line.split()
    if not words or words[0].startswith("#"):
        return None
    kind = words[0]
    if kind == "ODOM":
        if len(words) != 10:
            raise LineError(f"ODOM: expected 10 fields, got {len(words)}")
        pose = _pose_words(words, 1)
        text, stamp = _tail(words, 7, line_no)
        return OdometryRecord(text, stamp, pose, line_no)
    if kind in ("FLASER", "RLASER"):
        n = _count(words, 1)
        ranges = _floats(words, 2, 2 + n)
        text, stamp = _tail(words, 8 + n, line_no)
        return LaserRecord(kind, text, stamp, ranges, guess_beam_angles(n), None,
                           _pose_words(words, 2 + n), _pose_words(words, 5 + n), line_no)
    if kind.startswith(("ROBOTLASER", "RAWLASER")):
        head = _floats(words, 1, 7)  # type start fov resolution max_range accuracy (remission)
        n = _count(words, 8)
        ranges = _floats(words, 9, 9 + n)
        m = _count(words, 9 + n, allow_zero=True)
        i = 10 + n + m
        start, resolution, max_range = float(head[1]), float(head[3]), float(head[4])
        if not (math.isfinite(start) and math.isfinite(resolution) and resolution != 0.0):
            raise LineError("bad beam geometry")
        angles = start + resolution * np.arange(n, dtype=np.float64)
        max_r = max_range if math.isfinite(max_range) and max_range > 0 else None
        if kind.startswith("ROBOTLASER"):
            poses = _floats(words, i, i + 6)
            text, stamp = _tail(words, i + 11, line_no)
            return LaserRecord(kind, text, stamp, ranges, angles, max_r,
                               _pose(poses[:3]), _pose(poses[3:]), line_no)
        text, stamp = _tail(words, i, line_no)
        return LaserRecord(kind, text, stamp, ranges, angles, max_r, None, None, line_no)
    if not (kind.isascii() and kind.replace("_", "").replace("-", "").isalnum()):
        raise LineError(f"unreadable message name {kind[:20]!r}")
    if kind in ("LASER1", "LASER2", "LASER3", "LASER4"):
        n = _count(words, 1)
        ranges = _floats(words, 2, 2 + n)
        text, stamp = _tail(words, 2 + n, line_no)
        return LaserRecord(kind, text, stamp, ranges, guess_beam_angles(n), None, None, None,
                           line_no)
    return kind


@dataclass
class CarmenLog:
    """All laser and odometry records of a log, in file order, and the reader's statistics."""

    lasers: list[LaserRecord]
    odometry: list[OdometryRecord]
    params: dict[str, str]
    stats: ReadStats

    def laser_kinds(self) -> Counter[str]:
        return Counter(r.kind for r in self.lasers)


def iter_lines(path: Path, stats: ReadStats) -> Iterator[tuple[int, str]]:
    """Numbered lines of a log; a damaged compressed stream ends the iteration, noted in stats."""
    try:
        with open_text(path) as f:
            yield from enumerate(f, start=1)
    except (EOFError, OSError, ValueError) as e:  # truncated/corrupt .gz/.bz2 stream
        if stats.lines == 0 and isinstance(e, OSError) and not isinstance(e, EOFError):
            raise CarmenError(f"{path}: cannot read ({e})") from None
        stats.truncated_stream = True
        log.warning("%s: stream ends early after %d lines (%s)", path, stats.lines, e)


def read_log(path: str | Path) -> CarmenLog:
    """Read a CARMEN log; corrupt lines are skipped and counted in ``stats``."""
    p = Path(path)
    if not p.exists():
        raise CarmenError(f"{p}: no such file")
    if p.is_dir():
        raise CarmenError(f"{p}: is a directory, not a log file")
    stats = ReadStats()
    lasers: list[LaserRecord] = []
    odometry: list[OdometryRecord] = []
    params: dict[str, str] = {}
    try:
        for line_no, line in iter_lines(p, stats):
            stats.lines += 1
            try:
                rec = parse_line(line, line_no)
            except LineError as e:
                stats.skip("corrupt", line_no, f"{line.split()[0][:20]}: {e}")
                continue
            if rec is None:
                continue
            if isinstance(rec, str):
                stats.by_kind[rec] += 1
                if rec == "PARAM":
                    words = line.split()
                    if len(words) >= 3:
                        params[words[1]] = words[2]
                elif rec not in IGNORED_KINDS:
                    stats.skip("unknown message", line_no, f"unknown message type {rec[:20]!r}")
                continue
            stats.by_kind[rec.kind if isinstance(rec, LaserRecord) else "ODOM"] += 1
            (lasers if isinstance(rec, LaserRecord) else odometry).append(rec)  # type: ignore[arg-type]
    except PermissionError as e:
        raise CarmenError(f"{p}: cannot read ({e.strerror})") from None
    if not lasers:
        raise CarmenError(f"{p}: no laser scans found ({stats.lines} lines, "
                          f"{stats.skipped_total} unreadable)")
    return CarmenLog(lasers, odometry, params, stats)


@dataclass(frozen=True, slots=True)
class OdometryScan:
    """A laser scan with the odometry pose of the laser (odometry frame) at its stamp."""

    record: LaserRecord
    T_odom_laser: F64


def select_stream(log_: CarmenLog, laser: str = "front") -> list[LaserRecord]:
    """The scans of one laser: the first kind present of ``FRONT_KINDS`` (or ``REAR_KINDS``).

    Newer logs write the same scan in several formats (e.g. ROBOTLASER1 and RAWLASER1); taking
    one kind avoids using a scan twice. The richest format comes first.
    """
    kinds = FRONT_KINDS if laser == "front" else REAR_KINDS
    present = log_.laser_kinds()
    for kind in kinds:
        if present[kind]:
            return [r for r in log_.lasers if r.kind == kind]
    raise CarmenError(f"no {laser} laser scans in the log (found: {dict(present)})")


def _interpolate(stamps: F64, poses: F64, t: float) -> F64:
    """Odometry pose at time t: linear in x, y and along the shortest arc in θ; clamped to the
    first/last pose outside the recorded span."""
    j = int(np.searchsorted(stamps, t))
    if j <= 0 or j >= len(stamps):
        return poses[min(max(j, 0), len(stamps) - 1)]
    t0, t1 = stamps[j - 1], stamps[j]
    a = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
    p0, p1 = poses[j - 1], poses[j]
    d_theta = math.remainder(p1[2] - p0[2], 2 * math.pi)
    return np.array([p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]),
                     math.remainder(p0[2] + a * d_theta, 2 * math.pi)])


def laser_poses_are_stale(scans: list[LaserRecord], stamps: F64, poses: F64) -> bool:
    """True if most laser lines carry a verbatim copy of the last ODOM pose before them.

    Some loggers write the latest odometry into the laser line instead of the odometry at the
    scan's time; at walking speed that pose lags by up to one odometry period (several cm).
    """
    with_pose = [r for r in scans if r.robot_pose is not None]
    if not with_pose or len(stamps) == 0:
        return False
    copies = 0
    for r in with_pose:
        j = int(np.searchsorted(stamps, r.stamp_s, side="right")) - 1
        if j >= 0 and r.robot_pose is not None and np.array_equal(poses[j], r.robot_pose):
            copies += 1
    return copies > 0.5 * len(with_pose)


def attach_odometry(scans: list[LaserRecord], odometry: list[OdometryRecord],
                    laser_offset_x_m: float = 0.0, source: str = "auto") -> list[OdometryScan]:
    """Odometry pose of the laser for each scan.

    ``source="laser"`` takes the laser pose written in the laser line; ``"odom"`` interpolates
    the ``ODOM`` poses at the scan stamp and places the laser ``laser_offset_x_m`` ahead of the
    robot; ``"auto"`` takes the laser line's pose unless it is missing or a stale copy of the
    last ``ODOM`` line (see ``laser_poses_are_stale``).
    """
    stamps = np.array([o.stamp_s for o in odometry], dtype=np.float64)
    poses = np.array([o.pose for o in odometry], dtype=np.float64).reshape(-1, 3)
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order]
    if source == "auto":
        use_odom = len(stamps) > 0 and laser_poses_are_stale(scans, stamps, poses)
    elif source in ("laser", "odom"):
        use_odom = source == "odom"
    else:
        raise ValueError(f"unknown odometry source {source!r}")
    out: list[OdometryScan] = []
    for rec in scans:
        if rec.laser_pose is not None and not use_odom:
            out.append(OdometryScan(rec, rec.laser_pose))
            continue
        if len(stamps) == 0:
            raise CarmenError("laser lines carry no pose and the log has no ODOM lines")
        robot = _interpolate(stamps, poses, rec.stamp_s)
        c, s = math.cos(robot[2]), math.sin(robot[2])
        laser = np.array([robot[0] + c * laser_offset_x_m, robot[1] + s * laser_offset_x_m,
                          robot[2]])
        out.append(OdometryScan(rec, laser))
    return out
