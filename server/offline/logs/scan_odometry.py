"""Odometry from the scans alone, for recordings without any (a hand-held or bare scanner).

As Hector SLAM and Cartographer map such recordings, each scan is matched against the scans
before it, starting from a constant-velocity prediction: the motion per second between the
two scans before it, carried over the time to this one. The matcher is the SLAM front-end's own
(``server.slam.frontend.match_scan``: point-to-line ICP, a correlative search when that explains
too little, the prediction along a corridor's axis). The target is the latest key scan, which
is replaced once the sensor has moved ``key_distance_m`` or turned ``key_angle_deg`` from it;
matching against a key scan rather than the scan just before keeps a sensor that stands still
from drifting. A scan that cannot be matched takes the prediction.

The poses it gives are the laser's, in an odometry frame of its own, and are fed to
``RobotSlam`` as its odometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, pose_distance
from server.slam.config import SlamConfig
from server.slam.frontend import MatchKind, icp_params, match_scan, min_points
from server.slam.icp import PointMap
from server.slam.scan import ScanPoints, scan_to_points

F64 = NDArray[np.float64]
IDENTITY = np.zeros(3)


@dataclass(frozen=True)
class ScanOdometryParams:
    key_distance_m: float = 0.1
    key_angle_deg: float = 10.0


@dataclass
class ScanOdometryStats:
    matched: int = 0      # scans placed by a match
    predicted: int = 0    # scans that took the constant-velocity prediction


class ScanOdometry:
    """Feed scans in time order with ``add``; each returns the laser's pose (x, y, θ)."""

    def __init__(self, cfg: SlamConfig | None = None,
                 params: ScanOdometryParams | None = None) -> None:
        self.cfg = cfg or SlamConfig()
        self.params = params or ScanOdometryParams()
        self.stats = ScanOdometryStats()
        self._icp = icp_params(self.cfg.matcher)
        self._key: tuple[F64, PointMap] | None = None   # its pose and its points
        self._last: tuple[float, F64] | None = None      # stamp [s], pose
        self._rate = IDENTITY.copy()                      # motion per second (own frame)

    def add(self, stamp_s: float, ranges_m: F64, angles_rad: F64) -> F64:
        """The pose of the laser at this scan (the first scan is the origin)."""
        scan = self._points(ranges_m, angles_rad)
        if self._last is None:
            self._last = (stamp_s, IDENTITY.copy())
            self._take_key(IDENTITY, scan)
            return IDENTITY.copy()
        t_last, T_last = self._last
        dt = max(stamp_s - t_last, 0.0)
        step = self._rate * dt                                      # 1. predict
        T_pred = compose(T_last, step)
        T = self._match(scan, T_pred, T_last, step)                 # 2. match the key scan
        if dt > 0:
            self._rate = between(T_last, T) / dt                    # 3. the velocity
        self._last = (stamp_s, T)
        assert self._key is not None
        d, a = pose_distance(between(self._key[0], T))              # 4. a new key scan?
        if d >= self.params.key_distance_m or a >= math.radians(self.params.key_angle_deg):
            self._take_key(T, scan)
        return T

    def _points(self, ranges_m: F64, angles_rad: F64) -> ScanPoints:
        s = self.cfg.scan
        return scan_to_points(np.asarray(ranges_m, dtype=np.float64),
                              np.asarray(angles_rad, dtype=np.float64), s.min_range_m,
                              s.max_range_m, s.normal_window, s.normal_max_gap_m,
                              s.min_point_spacing_m)

    def _take_key(self, T: F64, scan: ScanPoints) -> None:
        if len(scan) >= min_points(scan, self.cfg.matcher) or self._key is None:
            ok = np.isfinite(scan.normals[:, 0])
            self._key = (T.copy(), PointMap(scan.points[ok], scan.normals[ok]))

    def _match(self, scan: ScanPoints, T_pred: F64, T_last: F64, step: F64) -> F64:
        """The pose of ``scan`` from a match against the key scan, or the prediction."""
        assert self._key is not None
        T_key, target = self._key
        m = match_scan(scan, target, between(T_key, T_pred), between(T_key, T_last), step,
                       False, self.cfg.matcher, self._icp)
        if m.kind == MatchKind.ODOMETRY:
            self.stats.predicted += 1
            return T_pred
        self.stats.matched += 1
        return compose(T_key, m.T_map_robot)
