"""Pure pursuit path following for a differential-drive robot.

The look-ahead point is the path point an arc length L past the point of the path closest to the
robot (the path's end when less than L remains). In the robot frame it lies at (x_r, y_r), at
distance D and bearing α = atan2(y_r, x_r). The arc through it has curvature

    κ = 2 · y_r / D²,     ω = v · κ,

with v fixed. When |ω| would exceed ω_max, ω is clipped and v lowered to ω_max/|κ| so the robot
still drives the same arc. When |α| exceeds ``rotate_in_place_above_rad`` (the path lies behind
or beside the robot) the robot turns on the spot, ω = clip(k·α, ω_max), until |α| is below
``resume_below_rad`` (hysteresis, so it does not swing wide when it sets off).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.control.geometry import STOP, Twist, clip
from server.jit import njit_cached


@dataclass(frozen=True)
class PursuitParams:
    lookahead_m: float = 1.0
    v_mps: float = 0.3
    omega_max_rps: float = 1.5
    goal_tolerance_m: float = 0.25
    rotate_in_place_above_rad: float = math.pi / 3
    resume_below_rad: float = 0.15
    rotate_gain: float = 2.0


@dataclass(frozen=True)
class PursuitStep:
    twist: Twist
    reached: bool
    lookahead_xy: tuple[float, float]
    heading_error_rad: float    # α: bearing of the look-ahead point in the robot frame
    cross_track_m: float        # distance from the robot to the path


def closest_point(path_xy: NDArray[np.float64], p: NDArray[np.float64], first_segment: int = 0,
                  last_segment: int | None = None) -> tuple[int, float, float]:
    """Closest point of segments [first, last] of a polyline to p.

    Returns (segment index i, fraction t ∈ [0, 1] along segment i, distance [m]).
    """
    path = np.ascontiguousarray(path_xy, dtype=np.float64).reshape(-1, 2)
    end = len(path) - 1 if last_segment is None else min(last_segment + 1, len(path) - 1)
    if end <= first_segment:
        raise ValueError("no segment to search")
    px, py = (float(v) for v in np.asarray(p, dtype=np.float64).reshape(2))
    k, t, dist = _closest(path, px, py, first_segment, end)
    return int(k), float(t), float(dist)


@njit_cached
def _closest(path: NDArray[np.float64], px: float, py: float, first: int, end: int
             ) -> tuple[int, float, float]:
    """Segments [first, end) of ``closest_point``: the first nearest, with the arithmetic of
    the vectorised search it replaces (to the bit)."""
    best, best_t, best_d = first, 0.0, np.inf
    for i in range(first, end):
        ax, ay = path[i, 0], path[i, 1]
        dx, dy = path[i + 1, 0] - ax, path[i + 1, 1] - ay
        L2 = dx * dx + dy * dy
        t = ((px - ax) * dx + (py - ay) * dy) / (L2 if L2 > 0 else 1.0)
        t = min(max(t, 0.0), 1.0)
        dist = np.hypot(ax + t * dx - px, ay + t * dy - py)
        if i == first or dist < best_d:
            best, best_t, best_d = i, t, dist
    return best, best_t, best_d


class PurePursuit:
    """Follows one path at a time; the progress along it only moves forward, so a path that
    passes near itself is not cut short. A different path array restarts the progress."""

    def __init__(self, params: PursuitParams | None = None) -> None:
        self.params = params or PursuitParams()
        self._path: NDArray[np.float64] | None = None
        self._cum: NDArray[np.float64] = np.zeros(1)
        self._cum_list: list[float] = [0.0]
        self._xy: list[list[float]] = []      # the path's points as floats
        self._segment = 0
        self._rotating = False

    def reset(self) -> None:
        self._path = None
        self._rotating = False

    def _load(self, path_xy: ArrayLike) -> NDArray[np.float64]:
        path = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
        if len(path) == 0 or not np.all(np.isfinite(path)):
            raise ValueError("path must hold at least one finite (x, y) point")
        if self._path is None or path.shape != self._path.shape or not np.array_equal(
                path, self._path):
            self._path = path.copy()
            seg = np.hypot(*np.diff(path, axis=0).T) if len(path) > 1 else np.zeros(0)
            self._cum = np.concatenate([[0.0], np.cumsum(seg)])
            self._xy = []
            self._segment = 0
            self._rotating = False
        if not getattr(self, "_xy", None):   # (also a state saved before the lists were kept)
            self._cum_list, self._xy = self._cum.tolist(), self._path.tolist()
        return self._path

    def reached(self, pose: ArrayLike, path_xy: ArrayLike) -> bool:
        goal = np.asarray(path_xy, np.float64).reshape(-1, 2)[-1]
        xy = np.asarray(pose, np.float64).reshape(3)[:2]
        return bool(np.hypot(*(goal - xy)) < self.params.goal_tolerance_m)

    def command(self, pose: ArrayLike, path_xy: ArrayLike) -> Twist:
        return self.step(pose, path_xy).twist

    def step(self, pose: ArrayLike, path_xy: ArrayLike) -> PursuitStep:
        # one robot's step in plain floats: the arithmetic of the array code it replaced
        # (``closest_point``, ``world_to_robot``, ``_point_at``), without its calls' overhead
        p = self.params
        path = self._load(path_xy)
        x, y, th = np.asarray(pose, np.float64).reshape(3).tolist()
        gx, gy = self._xy[-1]
        to_goal = float(np.hypot(gx - x, gy - y))
        if to_goal < p.goal_tolerance_m:
            return PursuitStep(STOP, True, (gx, gy), 0.0, to_goal)
        if len(path) == 1:
            tx, ty, cross = gx, gy, 0.0
        else:
            # Search forward from the current progress, up to one look-ahead beyond it, and
            # always into the next segment: a segment longer than the look-ahead would
            # otherwise hold the progress at its end for good, the look-ahead point fixed
            # a look-ahead past its corner (the robot drove there and turned on the spot)
            cum = self._cum_list
            s0 = cum[self._segment]
            last = bisect.bisect_right(cum, s0 + p.lookahead_m + 1.0) - 1
            last = min(max(last, self._segment + 1), len(path) - 2)
            seg, t, cross = _closest(path, x, y, self._segment, last + 1)
            self._segment = seg
            s = cum[seg] + t * (cum[seg + 1] - cum[seg]) + p.lookahead_m
            tx, ty = self._point_at_xy(s)
        dx, dy = tx - x, ty - y
        c, sn = math.cos(th), math.sin(th)
        xr, yr = c * dx + sn * dy, -sn * dx + c * dy
        alpha = math.atan2(yr, xr)
        tgt = (tx, ty)
        limit = p.resume_below_rad if self._rotating else p.rotate_in_place_above_rad
        self._rotating = abs(alpha) > limit
        if self._rotating:
            twist = Twist(0.0, clip(p.rotate_gain * alpha, p.omega_max_rps))
            return PursuitStep(twist, False, tgt, alpha, cross)
        d2 = xr * xr + yr * yr
        kappa = 2.0 * yr / d2 if d2 > 1e-12 else 0.0
        v, omega = p.v_mps, p.v_mps * kappa
        if abs(omega) > p.omega_max_rps:
            omega = math.copysign(p.omega_max_rps, omega)
            v = p.omega_max_rps / abs(kappa)
        return PursuitStep(Twist(v, omega), False, tgt, alpha, cross)

    def _point_at_xy(self, s: float) -> tuple[float, float]:
        """``_point_at`` in plain floats."""
        cum, xy = self._cum_list, self._xy
        if s >= cum[-1]:
            return xy[-1][0], xy[-1][1]
        i = bisect.bisect_right(cum, s) - 1
        i = min(max(i, 0), len(xy) - 2)
        span = cum[i + 1] - cum[i]
        t = (s - cum[i]) / span if span > 0 else 0.0
        (ax, ay), (bx, by) = xy[i], xy[i + 1]
        return ax + t * (bx - ax), ay + t * (by - ay)

    def _point_at(self, path: NDArray[np.float64], s: float) -> NDArray[np.float64]:
        """The path point at arc length s (clamped to the ends)."""
        cum = self._cum
        if s >= cum[-1]:
            return path[-1]
        i = int(np.searchsorted(cum, s, side="right")) - 1
        i = min(max(i, 0), len(path) - 2)
        span = cum[i + 1] - cum[i]
        t = (s - cum[i]) / span if span > 0 else 0.0
        return path[i] + t * (path[i + 1] - path[i])


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    closest_point(np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([0.5, 0.5]))


_warm_up()
