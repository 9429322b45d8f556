"""Vector field histogram obstacle avoidance (after Borenstein & Koren 1991, VFH+ 1998).

Obstacle points in the robot frame (the latest scan, other robots' positions) within
``window_m`` fill a polar histogram of ``sectors`` sectors. A point at distance d and bearing β,
enlarged by the radius r it must be kept from (robot radius + safety, plus the other robot's
radius for robots), blocks every sector within β ± γ, γ = asin(min(1, r/d)), when
d − r < ``block_distance_m``. Free sectors form valleys; the steering direction is the free
direction closest to the desired heading (the centre of a narrow valley, or s_max/2 sectors in
from the border of a wide one). Only when an obstacle is within ``activation_distance_m`` and the
desired heading is blocked does the command change: the robot turns towards the chosen direction
(on the spot beyond ``rotate_in_place_above_rad``), slowing as obstacles get closer. With every
sector blocked it turns on the spot towards the more open side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from schemas.se2 import wrap_angle
from server.control.geometry import Twist, clip
from server.jit import njit_cached


@dataclass(frozen=True)
class VfhParams:
    sectors: int = 72
    window_m: float = 1.5
    block_distance_m: float = 0.45
    activation_distance_m: float = 0.7
    robot_radius_m: float = 0.13
    safety_m: float = 0.07
    other_robot_radius_m: float = 0.13
    wide_valley_sectors: int = 12          # s_max
    v_mps: float = 0.3
    omega_max_rps: float = 1.5
    turn_gain: float = 1.5
    rotate_in_place_above_rad: float = math.pi / 3


@dataclass(frozen=True)
class VfhResult:
    twist: Twist
    active: bool                # the command was changed
    blocked: bool               # every sector blocked
    heading_rad: float          # chosen direction in the robot frame
    nearest_m: float            # distance to the nearest obstacle point


class Vfh:
    def __init__(self, params: VfhParams | None = None) -> None:
        self.params = params or VfhParams()
        n = self.params.sectors
        self._centres = np.asarray(-math.pi + (np.arange(n) + 0.5) * (2 * math.pi / n),
                                   dtype=np.float64)

    def blocked_sectors(self, points_robot_xy: ArrayLike, others_robot_xy: ArrayLike = ()
                        ) -> tuple[NDArray[np.bool_], float]:
        """Binary polar histogram (sectors,) and the distance to the nearest point [m]."""
        p = self.params
        pts = np.ascontiguousarray(points_robot_xy, dtype=np.float64).reshape(-1, 2)
        others = np.ascontiguousarray(others_robot_xy, dtype=np.float64).reshape(-1, 2)
        # Distance from the robot centre to each obstacle's surface; robots are discs.
        n = len(pts) + len(others)
        used = np.empty((4, n))        # x, y, distance, radius of the points that block
        count, nearest = _near(pts, others, p.other_robot_radius_m,
                               p.robot_radius_m + p.safety_m, p.window_m, p.block_distance_m,
                               used)
        blocked = np.zeros(p.sectors, dtype=bool)
        if count == 0:
            return blocked, nearest
        x, y, d, r = used[:, :count]
        beta = np.arctan2(y, x)
        gamma = np.arcsin(np.minimum(1.0, r / d))
        # Sector k is blocked by a point when |wrap(centre_k − β)| ≤ γ + half a sector.
        half = math.pi / p.sectors
        _block(self._centres, beta, gamma + half, blocked)
        return blocked, nearest

    def evaluate(self, twist: Twist, desired_heading_rad: float, points_robot_xy: ArrayLike,
                 others_robot_xy: ArrayLike = ()) -> VfhResult:
        """The avoidance command for a controller's ``twist`` that wants to go towards
        ``desired_heading_rad`` (robot frame), given obstacle points in the robot frame."""
        p = self.params
        blocked, nearest = self.blocked_sectors(points_robot_xy, others_robot_xy)
        desired = wrap_angle(desired_heading_rad)
        if nearest >= p.activation_distance_m or not blocked[self._sector(desired)]:
            return VfhResult(twist, False, False, desired, nearest)
        if blocked.all():
            side = 1.0 if self._openness(points_robot_xy, +1) >= self._openness(
                points_robot_xy, -1) else -1.0
            return VfhResult(Twist(0.0, side * p.omega_max_rps), True, True, desired, nearest)
        heading = self._choose(blocked, desired)
        if abs(heading) > p.rotate_in_place_above_rad:
            omega = clip(p.turn_gain * heading, p.omega_max_rps)
            return VfhResult(Twist(0.0, omega), True, False, heading, nearest)
        slow = min(1.0, max(0.3, nearest / p.activation_distance_m))
        omega = clip(p.turn_gain * heading, p.omega_max_rps)
        return VfhResult(Twist(p.v_mps * slow, omega), True, False, heading, nearest)

    def adjust(self, twist: Twist, desired_heading_rad: float, points_robot_xy: ArrayLike,
               others_robot_xy: ArrayLike = ()) -> Twist:
        return self.evaluate(twist, desired_heading_rad, points_robot_xy, others_robot_xy).twist

    def _sector(self, angle: float) -> int:
        n = self.params.sectors
        return int((angle + math.pi) / (2 * math.pi) * n) % n

    def _choose(self, blocked: NDArray[np.bool_], desired: float) -> float:
        """Free direction closest to ``desired`` (VFH+ valley rule)."""
        n = self.params.sectors
        smax = self.params.wide_valley_sectors
        # Rotate so the histogram starts at a blocked sector: valleys then never wrap around.
        start = int(np.flatnonzero(blocked)[0])
        free = np.roll(~blocked, -start)
        candidates: list[float] = []
        k = 0
        while k < n:
            if not free[k]:
                k += 1
                continue
            j = k
            while j + 1 < n and free[j + 1]:
                j += 1
            width = j - k + 1
            picks = [k + smax // 2, j - smax // 2] if width >= smax else [(k + j) // 2]
            candidates += [float(self._centres[(q + start) % n]) for q in picks]
            k = j + 1
        return min(candidates, key=lambda a: abs(wrap_angle(a - desired)))

    @staticmethod
    def _openness(points_robot_xy: ArrayLike, side: float) -> float:
        pts = _as_points(points_robot_xy)
        sel = pts[np.sign(pts[:, 1]) == side] if len(pts) else pts
        return float(np.mean(np.hypot(sel[:, 0], sel[:, 1]))) if len(sel) else math.inf


@njit_cached
def _near(pts: NDArray[np.float64], others: NDArray[np.float64], other_radius: float,
          base_radius: float, window: float, block_distance: float,
          used: NDArray[np.float64]) -> tuple[int, float]:
    """The finite points (then the other robots, discs of ``other_radius``) that block:
    their x, y, distance and radius into ``used``'s first columns; their count, and the
    distance to the nearest surface of any finite one."""
    count, nearest, any_point = 0, np.inf, False
    for j in range(pts.shape[0] + others.shape[0]):
        robot = j >= pts.shape[0]
        x, y = (others[j - pts.shape[0]] if robot else pts[j])[:2]
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        extra = other_radius if robot else 0.0
        d = np.hypot(x, y)
        surface = d - extra
        nearest = surface if not any_point or surface < nearest else nearest
        any_point = True
        radius = base_radius + extra
        if surface < window and d - radius < block_distance and d > 1e-6:
            used[0, count], used[1, count], used[2, count], used[3, count] = x, y, d, radius
            count += 1
    return count, nearest


@njit_cached
def _block(centres: NDArray[np.float64], beta: NDArray[np.float64],
           within: NDArray[np.float64], blocked: NDArray[np.bool_]) -> None:
    """``blocked[k]`` when |wrap(centres[k] − beta[i])| ≤ within[i] for some i, with the
    arithmetic of ``wrap_angle`` (to the bit)."""
    for i in range(beta.shape[0]):
        for k in range(centres.shape[0]):
            if blocked[k]:
                continue
            w = np.mod(centres[k] - beta[i] + np.pi, 2.0 * np.pi) - np.pi
            if w == -np.pi:
                w = np.pi
            if abs(w) <= within[i]:
                blocked[k] = True


def _as_points(xy: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return a[np.all(np.isfinite(a), axis=1)]


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    Vfh().blocked_sectors(np.array([[0.3, 0.1]]), np.array([[0.5, -0.2]]))
    _block(np.zeros(2), np.zeros(1), np.ones(1), np.zeros(2, dtype=bool))


_warm_up()
