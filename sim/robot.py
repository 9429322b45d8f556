"""Differential-drive kinematics, velocity/acceleration limits and collision tests."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.se2 import wrap_angle


@dataclass(frozen=True)
class DriveLimits:
    track_width_m: float = 0.27
    radius_m: float = 0.13          # body radius for collisions and for other robots' LIDARs
    v_max_mps: float = 0.5          # also the top speed of each wheel
    omega_max_rps: float = 2.0
    accel_max_mps2: float = 1.0
    alpha_max_rps2: float = 4.0


def limit_command(v_cmd: float, w_cmd: float, v_now: float, w_now: float,
                  lim: DriveLimits, dt_s: float) -> tuple[float, float]:
    """The body velocity reached after ``dt_s`` towards a command.

    The command is clipped to ±ω_max, then scaled (keeping its curvature) so that neither
    wheel, ``v ± ω b / 2``, exceeds ``v_max``; the change from the current velocity is then
    limited to ``a_max dt`` and ``α_max dt``.
    """
    w = min(max(w_cmd, -lim.omega_max_rps), lim.omega_max_rps)
    v = v_cmd
    wheel = abs(v) + abs(w) * lim.track_width_m / 2
    if wheel > lim.v_max_mps:
        k = lim.v_max_mps / wheel
        v, w = v * k, w * k
    dv_max, dw_max = lim.accel_max_mps2 * dt_s, lim.alpha_max_rps2 * dt_s
    v = v_now + min(max(v - v_now, -dv_max), dv_max)
    w = w_now + min(max(w - w_now, -dw_max), dw_max)
    return v, w


def arc_step(pose: tuple[float, float, float], v: float, w: float, dt_s: float
             ) -> tuple[float, float, float]:
    """Exact unicycle motion over ``dt_s`` at constant (v, ω): a chord ``v dt sinc(ω dt / 2)``
    along the mid-heading ``θ + ω dt / 2``."""
    x, y, th = pose
    dth = w * dt_s
    half = 0.5 * dth
    chord = v * dt_s * (math.sin(half) / half if abs(half) > 1e-12 else 1.0)
    mid = th + half
    return (x + chord * math.cos(mid), y + chord * math.sin(mid), wrap_angle(th + dth))


def point_in_polygons(points: np.ndarray, polygons: tuple[np.ndarray, ...]) -> np.ndarray:
    """(P,) True where a point lies inside any convex CCW polygon."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    inside = np.zeros(len(pts), bool)
    for poly in polygons:
        e = np.roll(poly, -1, axis=0) - poly
        rel = pts[:, None, :] - poly[None, :, :]
        cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]
        inside |= np.all(cross >= 0, axis=1)
    return inside


class Obstacles:
    """Static segments and circles, prepared for repeated disc-contact tests."""

    def __init__(self, segments: np.ndarray, circles: np.ndarray | None = None) -> None:
        seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
        self.a = seg[:, 0:2]
        self.e = seg[:, 2:4] - self.a
        self.ee = np.maximum((self.e ** 2).sum(axis=1), 1e-18)
        self.lo = np.minimum(seg[:, 0:2], seg[:, 2:4])
        self.hi = np.maximum(seg[:, 0:2], seg[:, 2:4])
        self.circles = np.zeros((0, 3)) if circles is None else np.asarray(
            circles, dtype=np.float64).reshape(-1, 3)

    def near(self, centres: np.ndarray, reach_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(disc index, segment index) pairs whose bounding boxes come within ``reach_m``."""
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
        x, y = c[:, 0:1], c[:, 1:2]
        near = ((x > self.lo[:, 0] - reach_m) & (x < self.hi[:, 0] + reach_m)
                & (y > self.lo[:, 1] - reach_m) & (y < self.hi[:, 1] + reach_m))
        ri, si = np.nonzero(near)
        return ri, si

    def touching(self, centres: np.ndarray, radius_m: float,
                 pairs: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(R,) True where a disc of ``radius_m`` at a centre touches a segment, a circle or
        another of the discs. ``pairs`` (from ``near`` with a reach >= the radius plus any
        motion since) limits the segments tested."""
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
        hit = np.zeros(len(c), bool)
        if len(self.a):
            r = radius_m
            ri, si = pairs if pairs is not None else self.near(c, r)
            if len(ri):
                p = c[ri] - self.a[si]
                e = self.e[si]
                t = np.clip((p * e).sum(axis=1) / self.ee[si], 0.0, 1.0)
                d = p - t[:, None] * e
                hit[ri[(d * d).sum(axis=1) < r * r]] = True
        if len(self.circles):
            cc = self.circles
            d = np.hypot(c[:, None, 0] - cc[None, :, 0], c[:, None, 1] - cc[None, :, 1])
            hit |= (d < radius_m + cc[None, :, 2]).any(axis=1)
        if len(c) > 1:
            d = np.hypot(c[:, None, 0] - c[None, :, 0], c[:, None, 1] - c[None, :, 1])
            np.fill_diagonal(d, np.inf)
            hit |= (d < 2 * radius_m).any(axis=1)
        return hit


def collisions(centres: np.ndarray, radius_m: float, segments: np.ndarray,
               circles: np.ndarray) -> np.ndarray:
    """(R,) True where a robot disc of ``radius_m`` touches a segment, a static circle or
    another robot's disc."""
    return Obstacles(segments, circles).touching(centres, radius_m)
