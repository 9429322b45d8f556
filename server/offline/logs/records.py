"""Records read from robot logs: laser scans, odometry, what the reader skipped."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
MAX_ERROR_EXAMPLES = 5


class CarmenError(Exception):
    """The log cannot be read at all (missing, unreadable, or without laser scans)."""

    user_error = True


class BagError(CarmenError):
    """A bag that cannot be used: not a bag, no laser scan topic, no odometry, unreadable."""


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


@dataclass
class CarmenLog:
    """All laser and odometry records of a log, in file order, and the reader's statistics."""

    lasers: list[LaserRecord]
    odometry: list[OdometryRecord]
    params: dict[str, str]
    stats: ReadStats

    def laser_kinds(self) -> Counter[str]:
        return Counter(r.kind for r in self.lasers)
