"""A turning camera's views, taken while the robot stands still, as one 360° scan.

A depth camera turned on a tower (see ``docs/mixed-sensors.md``) shows one narrow view at a
time. Matched one by one, such views often see a single wall, which pins the pose only across
it, and the robot's position drifts along it. While the robot drives, the views cannot be put
together: odometry's heading error between them smears the walls. While it stands still, its
odometry does not move, and the views of one turn of the tower are one 360° scan, short but
exact, that pins the pose in every direction where a room's walls are within reach.

``Sweep`` gathers the views while the odometry says the robot has not moved, and gives the
whole scan once they cover nearly the full circle. It also keeps the odometry distance since
the last whole scan and says when the robot should stop for the next (``due``): the steering
then holds it still until the scan is whole, or until ``wait_s`` has passed.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, pose_distance, rotate_vectors, transform_points
from server.slam.config import SweepConfig
from server.slam.scan import ScanPoints

F64 = NDArray[np.float64]

BINS = 36                      # the circle in 10° bins, for how much of it the views cover
TURNING_SPREAD_RAD = 1.0       # views this far apart in heading: the camera turns


@dataclass
class Sweep:
    """Views of a turning camera gathered while the robot stands still (see the module)."""

    cfg: SweepConfig
    views: list[tuple[ScanPoints, F64]] = field(default_factory=list)   # (view, its odometry)
    covered: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(BINS, dtype=bool))
    start_odom: F64 | None = None
    travelled_m: float = 0.0        # odometry distance since the last whole scan
    last_odom: F64 | None = None
    hold_since_ns: int | None = None
    headings: deque[float] = field(default_factory=lambda: deque(maxlen=2 * BINS))
    """the latest views' headings"""
    wholes: int = 0                 # whole scans given
    given_up: int = 0               # holds that ended without one
    skipped: int = 0                # stops the robot drove on through (not worth their time)

    @property
    def turning(self) -> bool:
        """Whether the camera turns (a fixed camera never covers the circle)."""
        if len(self.headings) < 2:
            return False
        h = np.asarray(self.headings)
        return bool(np.abs(np.angle(np.exp(1j * (h - h[-1])))).max() >= TURNING_SPREAD_RAD)

    def add(self, view: ScanPoints, odom: F64) -> ScanPoints | None:
        """Take one narrow view at odometry pose ``odom``; the whole scan, in the robot frame
        at ``odom``, once the views since the robot last moved cover the circle, else None."""
        c = self.cfg
        if self.last_odom is not None:
            self.travelled_m += pose_distance(between(self.last_odom, odom))[0]
        self.last_odom = odom
        self.headings.append(view.heading_rad)
        if self.start_odom is not None:
            d, a = pose_distance(between(self.start_odom, odom))
            if d > c.still_m or a > math.radians(c.still_deg):
                self.reset()
        if self.start_odom is None:
            self.start_odom = odom
        self.views.append((view, odom))
        half = min(view.fov_rad, 2 * math.pi) / 2
        centres = (np.arange(BINS) + 0.5) * (2 * math.pi / BINS)
        self.covered |= np.abs(np.angle(np.exp(1j * (centres - view.heading_rad)))) <= half
        if self.covered.mean() < c.coverage:
            return None
        whole = self._whole(odom)
        self.reset()
        self.travelled_m, self.hold_since_ns = 0.0, None
        self.wholes += 1
        return whole

    def due(self, stamp_ns: int) -> bool:
        """Whether the robot should stand still now for a whole scan: every ``every_m``,
        and at its start, before it first moves (whether the camera turns is not known yet
        then)."""
        c = self.cfg
        first = self.wholes == 0 and self.given_up == 0 and self.skipped == 0
        if not c.enabled or not (self.turning or first) or \
                (self.travelled_m < c.every_m and not first):
            self.hold_since_ns = None
            return False
        if self.hold_since_ns is None:
            self.hold_since_ns = stamp_ns
        if stamp_ns - self.hold_since_ns > c.wait_s * 1e9:   # it does not come: drive on
            self.travelled_m, self.hold_since_ns = 0.0, None
            self.given_up += 1
            return False
        return True

    def skip(self) -> None:
        """The robot drives on instead of stopping now: asked again after ``every_m``."""
        self.travelled_m, self.hold_since_ns = 0.0, None
        self.skipped += 1

    def reset(self) -> None:
        self.views, self.start_odom = [], None
        self.covered = np.zeros(BINS, dtype=bool)

    def _whole(self, odom: F64) -> ScanPoints:
        parts = []
        for view, at in self.views:
            T = between(odom, at)    # ≈ identity: the robot stood still
            parts.append((transform_points(T, view.points), rotate_vectors(T[2], view.normals),
                          view.ranges_m,
                          transform_points(T, view.hits), transform_points(T, view.misses)))
        pts, nrm, rng, hits, misses = (np.concatenate([p[i] for p in parts]) for i in range(5))
        return ScanPoints(pts, nrm, rng, hits, misses, 2 * math.pi, 0.0)
