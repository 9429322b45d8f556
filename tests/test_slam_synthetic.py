"""Synthetic 2D worlds for the SLAM tests: walls as segments, an exact ray caster, and a robot
driving along a path with drifting odometry. Other test modules import these helpers."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, wrap_angle

F64 = NDArray[np.float64]
Segment = tuple[tuple[float, float], tuple[float, float]]


def box(x0: float, y0: float, x1: float, y1: float) -> list[Segment]:
    return [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)),
            ((x0, y1), (x0, y0))]


def room_world() -> list[Segment]:
    """A 10 × 6 m room with a pillar and an alcove (no symmetry, no corridor)."""
    walls = [((0.0, 0.0), (10.0, 0.0)), ((10.0, 0.0), (10.0, 6.0)), ((10.0, 6.0), (3.0, 6.0)),
             ((3.0, 6.0), (3.0, 7.0)), ((3.0, 7.0), (0.0, 7.0)), ((0.0, 7.0), (0.0, 0.0))]
    return walls + box(6.0, 2.0, 6.8, 2.6)


def ring_world() -> list[Segment]:
    """A rectangular ring corridor (outer 14 × 10 m, inner block 10 × 6 m) with a few niches
    and pillars along it, so that no stretch of corridor is featureless."""
    walls = box(0.0, 0.0, 14.0, 10.0) + box(2.0, 2.0, 12.0, 8.0)
    for x in (3.5, 7.0, 10.5):
        walls += box(x, 0.0, x + 0.3, 0.4)  # pillars on the outer wall, bottom
        walls += box(x + 0.7, 9.6, x + 1.0, 10.0)  # and top
    for y in (4.0, 6.5):
        walls += box(0.0, y, 0.4, y + 0.3)
        walls += box(13.6, y - 1.5, 14.0, y - 1.2)
    walls += box(5.0, 2.0, 5.5, 2.3) + box(8.0, 7.7, 8.6, 8.0)
    return walls


def cast(walls: list[Segment], T_world_sensor: F64, angles_rad: F64,
         max_range_m: float = 30.0) -> F64:
    """Exact ranges [m] from ``T_world_sensor`` along ``angles_rad``; inf without a hit."""
    T = np.asarray(T_world_sensor, dtype=np.float64)
    ang = angles_rad + T[2]
    dx, dy = np.cos(ang), np.sin(ang)
    best = np.full(len(angles_rad), np.inf)
    for (ax, ay), (bx, by) in walls:
        ex, ey = bx - ax, by - ay
        ox, oy = ax - T[0], ay - T[1]
        den = dx * (-ey) - dy * (-ex)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ox * (-ey) - oy * (-ex)) / den
            u = (dx * oy - dy * ox) / den
        hit = np.isfinite(t) & (t > 1e-9) & (u >= 0) & (u <= 1)
        best = np.where(hit & (t < best), t, best)
    best[best > max_range_m] = np.inf
    return best


@dataclass
class Drive:
    """Ground truth and odometry of a robot driving a path; scans taken at every pose."""

    truth: F64  # (N, 3)
    odom: F64  # (N, 3)
    ranges: list[F64]
    angles: F64


def waypoints_path(points: list[tuple[float, float]], step_m: float) -> F64:
    """Poses every ``step_m`` along a polyline, heading along it (turns happen in place over a
    few steps so the scan matcher sees them)."""
    out: list[tuple[float, float, float]] = []
    for (x0, y0), (x1, y1) in itertools.pairwise(points):
        heading = math.atan2(y1 - y0, x1 - x0)
        if out:
            prev = out[-1][2]
            turn = wrap_angle(heading - prev)
            n_turn = max(1, int(abs(turn) / math.radians(8)))
            for k in range(1, n_turn + 1):
                out.append((x0, y0, prev + turn * k / n_turn))
        length = math.hypot(x1 - x0, y1 - y0)
        n = max(1, int(length / step_m))
        for k in range(0 if not out else 1, n + 1):
            a = k / n
            out.append((x0 + a * (x1 - x0), y0 + a * (y1 - y0), heading))
    return np.array(out)


def drive(walls: list[Segment], truth: F64, n_beams: int = 360, fov_rad: float = 2 * math.pi,
          range_noise_m: float = 0.01, odom_drift_rad_per_m: float = 0.02,
          odom_scale: float = 1.02, seed: int = 0) -> Drive:
    """Scans along ``truth`` and odometry that over-counts distance by ``odom_scale`` and turns
    by ``odom_drift_rad_per_m`` per metre travelled (a biased, drifting odometry)."""
    rng = np.random.default_rng(seed)
    if fov_rad >= 2 * math.pi - 1e-9:
        angles = -math.pi + 2 * math.pi * np.arange(n_beams) / n_beams
    else:
        angles = -fov_rad / 2 + fov_rad * np.arange(n_beams) / (n_beams - 1)
    odom = [truth[0].copy()]
    for a, b in itertools.pairwise(truth):
        step = between(a, b)
        dist = math.hypot(step[0], step[1])
        noisy = np.array([step[0] * odom_scale, step[1] * odom_scale,
                          step[2] + odom_drift_rad_per_m * dist])
        odom.append(compose(odom[-1], noisy))
    ranges = []
    for T in truth:
        r = cast(walls, T, angles)
        ranges.append(r + rng.normal(0.0, range_noise_m, len(r)))
    return Drive(truth, np.array(odom), ranges, angles)


def align_error(est: F64, truth: F64) -> F64:
    """Position errors [m] of ``est`` after expressing both in their first pose's frame."""
    e = compose(np.broadcast_to(np.asarray(truth[0]), truth.shape), between(est[0], est))
    return np.hypot(e[:, 0] - truth[:, 0], e[:, 1] - truth[:, 1])


def test_cast_hits_known_walls() -> None:
    walls = box(0.0, 0.0, 4.0, 2.0)
    r = cast(walls, np.array([1.0, 1.0, 0.0]), np.array([0.0, math.pi / 2, math.pi, -math.pi / 2]))
    np.testing.assert_allclose(r, [3.0, 1.0, 1.0, 1.0], atol=1e-12)


def test_drive_odometry_drifts() -> None:
    truth = waypoints_path([(1.0, 1.0), (9.0, 1.0)], 0.1)
    d = drive(room_world(), truth, n_beams=90)
    assert np.hypot(*(d.odom[-1, :2] - truth[-1, :2])) > 0.1
    assert len(d.ranges) == len(truth)
