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
import dataclasses
import functools
import gzip
import io
import logging
import math
import sys
from collections.abc import Generator
from pathlib import Path
from typing import IO

import numpy as np

from server.offline.logs.kept import Keeping, KeptText
from server.offline.logs.records import (
    F64,
    CarmenError,
    CarmenLog,
    LaserRecord,
    LineError,
    OdometryRecord,
    ReadStats,
)

log = logging.getLogger(__name__)

IGNORED_KINDS = frozenset({"PARAM", "SYNC", "TRUEPOS", "NMEAGGA", "NMEARMC", "NMEA-GGA",
                           "SONAR", "BUMPER", "IMU", "ARM", "POSITIONLASER", "GPSNMEA"})


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


@functools.lru_cache(maxsize=64)
def beam_angles(start: float, resolution: float, n_beams: int) -> F64:
    """Beam angles [rad] of a scan that states its geometry (ROBOTLASER, RAWLASER): one
    read-only array shared by the scans of a stream (a long log holds tens of thousands)."""
    angles = start + resolution * np.arange(n_beams, dtype=np.float64)
    angles.flags.writeable = False
    return angles


def open_text(path: Path, kept: KeptText | None = None) -> IO[str]:
    """Open a possibly compressed log as text; undecodable bytes become U+FFFD (then fail).
    ``kept``: a compressed log's decompressed bytes are kept there as they are read (if they
    fit), or read from there if it holds them whole already."""
    suffix = path.suffix.lower()
    raw: IO[bytes]
    # the streams are returned to the caller, who closes them
    again = kept.reader() if kept is not None else None
    if again is not None:
        raw = again
    elif suffix == ".gz":
        raw = gzip.open(path, "rb")  # type: ignore[assignment]  # noqa: SIM115
    elif suffix == ".bz2":
        raw = bz2.open(path, "rb")  # noqa: SIM115
    else:
        raw = open(path, "rb")  # noqa: SIM115
    if kept is not None and again is None and suffix in (".gz", ".bz2"):
        raw = io.BufferedReader(Keeping(raw, kept))
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
        angles = beam_angles(start, resolution, n)
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


def iter_lines(path: Path, stats: ReadStats, kept: KeptText | None = None
               ) -> Generator[tuple[int, str], None, None]:
    """Numbered lines of a log; a damaged compressed stream ends the iteration, noted in stats.
    ``kept``: as ``open_text``."""
    try:
        with open_text(path, kept) as f:
            yield from enumerate(f, start=1)
    except (EOFError, OSError, ValueError) as e:  # truncated/corrupt .gz/.bz2 stream
        if stats.lines == 0 and isinstance(e, OSError) and not isinstance(e, EOFError):
            raise CarmenError(f"{path}: cannot read ({e})") from None
        stats.truncated_stream = True
        log.warning("%s: stream ends early after %d lines (%s)", path, stats.lines, e)


#: the ranges of a scan read without them (``read_log(keep_ranges=False)``)
NO_RANGES: F64 = np.zeros(0)
NO_RANGES.flags.writeable = False


def read_log(path: str | Path, keep_ranges: bool = True, kept: KeptText | None = None
             ) -> CarmenLog:
    """Read a CARMEN log; corrupt lines are skipped and counted in ``stats``.

    ``keep_ranges=False``: every line is read and checked as usual, but the scans keep no
    ranges (``NO_RANGES``); ``LaserLines`` reads them again, scan by scan, when they are used.
    A long log's scans then take a few hundred bytes each instead of a few kilobytes.
    ``kept``: where a compressed log's text is kept for that second pass (``KeptText``)."""
    p = Path(path)
    if not p.exists():
        raise CarmenError(f"{p}: no such file")
    if p.is_dir():
        raise CarmenError(f"{p}: is a directory: neither a log file nor a ROS 2 bag folder "
                          f"(no metadata.yaml in it)")
    stats = ReadStats()
    lasers: list[LaserRecord] = []
    odometry: list[OdometryRecord] = []
    params: dict[str, str] = {}
    try:
        for line_no, line in iter_lines(p, stats, kept):
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
            if not keep_ranges and isinstance(rec, LaserRecord):
                rec = dataclasses.replace(rec, kind=sys.intern(rec.kind), ranges_m=NO_RANGES)
            (lasers if isinstance(rec, LaserRecord) else odometry).append(rec)  # type: ignore[arg-type]
    except PermissionError as e:
        raise CarmenError(f"{p}: cannot read ({e.strerror})") from None
    if not lasers:
        raise CarmenError(f"{p}: no laser scans found ({stats.lines} lines, "
                          f"{stats.skipped_total} unreadable)")
    return CarmenLog(lasers, odometry, params, stats)


class LaserLines:
    """The ranges of a log's scans read again from the file, in file order: the second pass
    of a log read with ``read_log(keep_ranges=False)``. Each call reads forward to the scan's
    line; asking for an earlier line than the last is an error, as is a line that no longer
    holds that scan (the file changed between the passes). ``kept``: the first pass's text,
    read from there if it holds it whole (``KeptText``), else from the file."""

    def __init__(self, path: str | Path, kept: KeptText | None = None) -> None:
        self.path = Path(path)
        self._kept = kept
        self._lines = iter_lines(self.path, ReadStats(), kept)
        self._at = 0

    def ranges(self, rec: LaserRecord) -> F64:
        """The ranges of ``rec`` (a scan of this log, read without its ranges)."""
        if rec.line_no <= self._at:
            raise ValueError(f"line {rec.line_no} asked after line {self._at}")
        for line_no, line in self._lines:
            self._at = line_no
            if line_no < rec.line_no:
                continue
            try:
                again = parse_line(line, line_no)
            except LineError:
                again = None
            if isinstance(again, LaserRecord) and again.stamp_text == rec.stamp_text:
                return again.ranges_m
            break
        raise CarmenError(f"{self.path}: line {rec.line_no} no longer holds the scan read "
                          f"there (the file changed while it was read)")

    def close(self) -> None:
        self._lines.close()
        if self._kept is not None:
            self._kept.drop()
