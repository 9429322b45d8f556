"""Noticing that a placed robot is no longer where the server believes it is.

A robot moved by hand, or knocked away, goes on with its odometry as if nothing happened: the
server places it where it was plus what its wheels say, and its scans stop agreeing with the
map there. Each scan of a placed robot is laid on the known map at that pose: a return near a
mapped wall agrees, a return in open space with no wall near (``Layers``' clear cells)
disagrees; returns on ground the map does not know say nothing (a robot extending the map sees
new ground). When more than ``conflict_ratio`` of the scan's returns on mapped ground disagree,
scan after scan for ``after_s``, the robot is lost. One scan that agrees starts the count
again: a passing person or a moved box spoils some returns, not most of them. No I/O here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import transform_points
from server.rendezvous.mapmatch import Layers, _cells
from server.rendezvous.submaps import CLEAR, NEAR, _codes

F64 = NDArray[np.float64]

#: returns on mapped ground a scan needs before it can say anything
MIN_KNOWN_RETURNS = 30


@dataclass(frozen=True)
class Agreement:
    agree: int        # returns near a mapped wall
    conflict: int     # returns in the map's open space, no wall near

    @property
    def known(self) -> int:
        return self.agree + self.conflict

    @property
    def conflict_ratio(self) -> float:
        return self.conflict / self.known if self.known else 0.0


def scan_agreement(lay: Layers, T_map_robot: F64, points_robot: F64) -> Agreement:
    """How a scan's returns (robot frame) lie on the map's fine layers at ``T_map_robot``."""
    if not len(points_robot):
        return Agreement(0, 0)
    i, j, _ = _cells(lay, transform_points(T_map_robot, points_robot))
    h, w = lay.code.shape
    n = _codes(lay.code, i, j, h, w)
    return Agreement(int(n[NEAR].sum()), int(n[CLEAR & ~NEAR].sum()))


@dataclass
class LossWatch:
    """One placed robot's run of scans that disagree with the map."""

    conflict_ratio: float
    after_s: float
    bad_since_ns: int | None = None
    good_keyframes: int = 0      # the robot's keyframes as of its last scan that agreed
    last: Agreement = Agreement(0, 0)

    def update(self, a: Agreement, stamp_ns: int, keyframes: int) -> bool:
        """Take one scan's agreement; True once the robot is lost."""
        self.last = a
        if a.known < MIN_KNOWN_RETURNS:
            return False            # nothing mapped in view: no evidence either way
        if a.conflict_ratio <= self.conflict_ratio:
            self.bad_since_ns, self.good_keyframes = None, keyframes
            return False
        if self.bad_since_ns is None:
            self.bad_since_ns = stamp_ns
        return stamp_ns - self.bad_since_ns >= self.after_s * 1e9


def scan_points(ranges_m: F64, angles_rad: F64, max_range_m: float) -> F64:
    """A scan's returns (finite, within range) in the robot frame (N, 2)."""
    ok = np.isfinite(ranges_m) & np.isfinite(angles_rad) & (ranges_m < max_range_m)
    r, a = ranges_m[ok], angles_rad[ok]
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
