"""Corrupt odometry samples in a recording: found, skipped and counted.

Real recordings carry odometry samples that no robot produced: a flipped bit in a float gives
``y = 1.9e32``, a field read as zero puts the robot back at the origin for one sample. Used as
they are, one such sample bends a scan's predicted pose by metres (or makes it NaN). Each
sample, in stamp order, is judged against the last one kept:

1. **non-finite** — a NaN or infinite stamp or pose is skipped;
2. **absurd** — a position farther than ``max_abs_m`` from the odometry's origin (by default
   20,000 km: no two places on Earth are farther apart, so even a UTM or ECEF frame stays
   inside) is skipped;
3. **jump** — a step from the last kept sample that the robot cannot drive in the time between
   them (more than ``max_speed_m_s`` · Δt + ``slack_m``, or ``max_turn_rate_deg_s`` · Δt +
   ``slack_deg``) is skipped when most of the ``window`` samples after it lie nearer the last
   kept sample than it (nearer: less far beyond the robot's reach). A jump that the
   following samples continue from is kept: odometry that stalled and caught up, or a
   driver that restarted at zero, is what the robot's odometry said, and the SLAM front-end
   treats a step that large as suspect on its own.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import wrap_angle

F64 = NDArray[np.float64]
REASONS = ("non_finite", "absurd", "jump")


@dataclass(frozen=True)
class OdometryLimits:
    """What a robot's odometry can do between two samples."""

    max_speed_m_s: float = 5.0
    max_turn_rate_deg_s: float = 360.0
    slack_m: float = 0.1
    slack_deg: float = 10.0
    max_abs_m: float = 2.0e7
    window: int = 5


@dataclass
class OdometryCheck:
    """Which samples were kept (indices into the input) and why the others were skipped."""

    keep: list[int] = field(default_factory=list)
    skipped: Counter[str] = field(default_factory=Counter)
    #: (index, reason) of the first few skipped samples, for the log
    examples: list[tuple[int, str]] = field(default_factory=list)

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())

    def skip(self, i: int, reason: str) -> None:
        self.skipped[reason] += 1
        if len(self.examples) < 5:
            self.examples.append((i, reason))


def _excess(a: F64, b: F64, dt_s: float, lim: OdometryLimits) -> float:
    """How far beyond the robot's reach pose ``b`` is from pose ``a`` after ``dt_s`` seconds:
    the larger of distance / reach and turn / turn reach (≤ 1: within reach)."""
    dt = abs(dt_s)
    d = math.hypot(b[0] - a[0], b[1] - a[1])
    turn = abs(wrap_angle(float(b[2] - a[2])))
    return max(d / (lim.max_speed_m_s * dt + lim.slack_m + 1e-12),
               turn / math.radians(lim.max_turn_rate_deg_s * dt + lim.slack_deg + 1e-9))


def check_odometry(stamps_s: F64, poses: F64, limits: OdometryLimits | None = None
                   ) -> OdometryCheck:
    """Judge samples given in stamp order (``stamps_s`` (N,), ``poses`` (N, 3)); see the module
    docstring."""
    lim = limits or OdometryLimits()
    out = OdometryCheck()
    t = np.asarray(stamps_s, dtype=np.float64)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    finite = np.isfinite(t) & np.isfinite(p).all(axis=1)
    with np.errstate(invalid="ignore"):
        sane = finite & (np.abs(p[:, :2]) <= lim.max_abs_m).all(axis=1)
    usable = np.flatnonzero(sane)
    last: int | None = None
    for k, i in enumerate(usable):
        following = usable[k + 1:k + 1 + lim.window]
        if last is None:
            # the first sample: kept unless the ones after it agree more among themselves
            # than with it
            with_it = sum(_excess(p[i], p[j], t[j] - t[i], lim) <= 1 for j in following)
            among = sum(_excess(p[following[0]], p[j], t[j] - t[following[0]], lim) <= 1
                        for j in following[1:])
            ok = among <= with_it
        elif _excess(p[last], p[i], t[i] - t[last], lim) <= 1:
            ok = True
        else:
            # beyond reach: a spike if most samples after it lie nearer the kept one
            nearer_kept = sum(_excess(p[last], p[j], t[j] - t[last], lim)
                              < _excess(p[i], p[j], t[j] - t[i], lim) for j in following)
            ok = 2 * nearer_kept <= len(following)
        if ok:
            out.keep.append(int(i))
            last = int(i)
        else:
            out.skip(int(i), "jump")
    for i in np.flatnonzero(~sane):
        out.skip(int(i), "non_finite" if not finite[i] else "absurd")
    out.examples.sort()
    return out
