"""From ranges to points with normals, in the sensor frame.

Normals come from the scan's own order: a line fitted to the valid neighbours within a few beams
(principal axis of their 2×2 covariance). Neighbours across a range discontinuity are excluded,
so normals are not smeared over corners or depth jumps. A 2D normal is what point-to-line
matching needs; estimators that treat the scan as a 3D cloud return the useless z axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached
from server.slam.errors import SlamInputError

F64 = NDArray[np.float64]


class ScanError(SlamInputError):
    """A scan cannot be used (ranges and angles differ in shape...)."""


@dataclass(frozen=True, slots=True)
class ScanPoints:
    """Returns of one scan in the sensor frame.

    ``points`` (N, 2) [m]: the returns used for matching (thinned to a spacing); ``normals``
    (N, 2) unit vectors facing the sensor, NaN where no line could be fitted; ``ranges_m`` (N,)
    their ranges; ``hits`` (M, 2): every valid return, for the occupancy grid; ``misses``
    (K, 2): for beams without a return, the point at the range up to which the sensor saw
    nothing (free space only, never an obstacle); ``fov_rad``: the angle the beams span (a
    depth camera's ~1.5 rad, a LIDAR's 2π).
    """

    points: F64
    normals: F64
    ranges_m: F64
    hits: F64
    misses: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    fov_rad: float = 2 * np.pi
    heading_rad: float = 0.0   # the middle of the field of view (sensor frame)

    def __len__(self) -> int:
        return len(self.points)

    def with_normals(self) -> ScanPoints:
        ok = np.isfinite(self.normals[:, 0])
        return ScanPoints(self.points[ok], self.normals[ok], self.ranges_m[ok], self.hits,
                          self.misses, self.fov_rad, self.heading_rad)


def valid_returns(ranges_m: F64, angles_rad: F64, min_range_m: float,
                  max_range_m: float) -> tuple[F64, F64]:
    """Ranges and angles of the beams with a return: finite and in [min, max)."""
    r = np.asarray(ranges_m, dtype=np.float64)
    a = np.asarray(angles_rad, dtype=np.float64)
    if r.shape != a.shape or r.ndim != 1:
        raise ScanError(f"ranges {r.shape} and angles {a.shape} must be equal 1-D arrays")
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & np.isfinite(a) & (r >= min_range_m) & (r < max_range_m)
    return r[ok], a[ok]


def line_normals(points: F64, window: int, max_gap_m: F64 | float,
                 centers: NDArray[np.int64] | None = None) -> F64:
    """Unit normals (M, 2) at ``centers`` (default: all N points) of ordered points, from a
    line fit over up to ±``window`` neighbours.

    Neighbours are taken outwards from the centre while each stays within ``max_gap_m``
    (scalar or per point) of it, so a range jump ends the run. The normal is the eigenvector of
    the smallest eigenvalue of C = Σ (q_j − q̄)(q_j − q̄)ᵀ, facing the sensor (n · p < 0). NaN
    where fewer than 3 points are usable or the fit is not line-like (λ_min > 0.2 λ_max).
    Compiled (``_normals``): a scan's few hundred points cost microseconds, not the hundreds of
    a loop of numpy calls.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    idx = np.arange(n) if centers is None else np.asarray(centers, dtype=np.int64)
    gap = np.ascontiguousarray(np.broadcast_to(np.asarray(max_gap_m, dtype=np.float64), (n,)))
    return _normals(pts, int(window), gap, idx)


@njit_cached
def _normals(points: F64, window: int, gap: F64, idx: NDArray[np.int64]) -> F64:
    n, m = len(points), len(idx)
    out = np.full((m, 2), np.nan)
    if n < 3 or m == 0:
        return out
    for i in range(m):
        c = idx[i]
        cx, cy = points[c, 0], points[c, 1]
        g2 = gap[c] * gap[c]
        cnt, sx, sy = 1.0, cx, cy
        sxx, syy, sxy = cx * cx, cy * cy, cx * cy
        for sign in (1, -1):
            for k in range(1, window + 1):
                j = c + sign * k
                if j < 0 or j >= n:
                    break
                qx, qy = points[j, 0], points[j, 1]
                if (qx - cx) ** 2 + (qy - cy) ** 2 > g2:
                    break
                cnt += 1.0
                sx += qx
                sy += qy
                sxx += qx * qx
                syy += qy * qy
                sxy += qx * qy
        if cnt < 3:
            continue
        mx, my = sx / cnt, sy / cnt
        cxx, cyy, cxy = sxx / cnt - mx * mx, syy / cnt - my * my, sxy / cnt - mx * my
        # eigen-decomposition of [[cxx, cxy], [cxy, cyy]] in closed form
        tr, det = cxx + cyy, cxx * cyy - cxy * cxy
        disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
        lmin, lmax = tr / 2 - disc, tr / 2 + disc
        # the line direction is the eigenvector of lmax; the normal is perpendicular to it
        ux, uy = cxy, lmax - cxx
        if abs(ux) + abs(uy) < 1e-12:
            ux, uy = lmax - cyy, cxy
        norm = math.hypot(ux, uy)
        if not (norm > 1e-12 and lmin <= 0.2 * lmax):
            continue
        nx, ny = -uy / norm, ux / norm
        if nx * cx + ny * cy > 0:
            nx, ny = -nx, -ny
        out[i, 0], out[i, 1] = nx, ny
    return out


def thin_by_spacing(points: F64, spacing_m: float) -> NDArray[np.bool_]:
    """Keep-mask dropping ordered points closer than ``spacing_m`` to the last kept one.

    Approximated in one pass: a point is kept when the path length since the previous kept
    point (cumulative along the scan) crosses a multiple of ``spacing_m``.
    """
    n = len(points)
    if n == 0 or spacing_m <= 0:
        return np.ones(n, dtype=bool)
    d = np.diff(points, axis=0)
    step = np.hypot(d[:, 0], d[:, 1])
    step = np.minimum(step, spacing_m)  # a jump always starts a new bin
    s = np.concatenate([[0.0], np.cumsum(step)])
    bins = np.floor(s / spacing_m).astype(np.int64)
    keep = np.ones(n, dtype=bool)
    keep[1:] = bins[1:] != bins[:-1]
    return keep


def scan_to_points(ranges_m: F64, angles_rad: F64, min_range_m: float, max_range_m: float,
                   normal_window: int = 2, normal_max_gap_m: float = 0.3,
                   min_spacing_m: float = 0.0, no_return_free_m: float = 0.0) -> ScanPoints:
    """Points (sensor frame) and normals of the beams with a return, thinned to a spacing.

    With ``no_return_free_m`` > 0, beams without a return (+inf, or at/after ``max_range_m``)
    give ``misses`` at that range: the sensor would have seen anything closer. NaN and
    readings below ``min_range_m`` say nothing and give neither.
    """
    r, a = valid_returns(ranges_m, angles_rad, min_range_m, max_range_m)
    misses = np.zeros((0, 2))
    if no_return_free_m > 0:
        ra = np.asarray(ranges_m, dtype=np.float64)
        aa = np.asarray(angles_rad, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            none = np.isfinite(aa) & ((ra == np.inf) | (np.isfinite(ra) & (ra >= max_range_m)))
        am = aa[none]
        misses = no_return_free_m * np.stack([np.cos(am), np.sin(am)], axis=1)
    pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    # the gap allowed between neighbours grows with range, as the beams spread apart
    beam_step = abs(float(a[-1] - a[0])) / (len(a) - 1) if len(a) > 1 else 0.0
    gap = np.maximum(normal_max_gap_m, 2.5 * normal_window * beam_step * r)
    keep = np.flatnonzero(thin_by_spacing(pts, min_spacing_m))
    normals = line_normals(pts, normal_window, gap, keep)
    return ScanPoints(pts[keep], normals, r[keep], pts, misses, *field_of_view(angles_rad))


def field_of_view(angles_rad: F64) -> tuple[float, float]:
    """The angle a scan's beams span, one beam's width included (at most 2π), and the
    direction of its middle."""
    a = np.asarray(angles_rad, dtype=np.float64)
    a = a[np.isfinite(a)]
    if len(a) < 2:
        return 0.0, float(a[0]) if len(a) else 0.0
    inc = abs(float(a[-1] - a[0])) / (len(a) - 1)
    return min(abs(float(a[-1] - a[0])) + inc, 2 * np.pi), 0.5 * float(a[0] + a[-1])



# compiled now, at import, not on a first scan (see ``server.slam.icp._warm_up``)
line_normals(np.array([[1.0, -0.2], [1.0, -0.1], [1.0, 0.0], [1.0, 0.1], [1.0, 0.2]]), 2, 0.5)
