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


def _writable(x: F64) -> F64:
    """``x``, or a copy where it is read-only (a wire message's buffer, a shared angle table):
    numba types a read-only array apart, and every such variant of ``_scan_kernel`` would be
    compiled again on its first scan, outside the warm-up at import."""
    return x if x.flags.writeable else x.copy()


def scan_to_points(ranges_m: F64, angles_rad: F64, min_range_m: float, max_range_m: float,
                   normal_window: int = 2, normal_max_gap_m: float = 0.3,
                   min_spacing_m: float = 0.0, no_return_free_m: float = 0.0) -> ScanPoints:
    """Points (sensor frame) and normals of the beams with a return, thinned to a spacing.

    With ``no_return_free_m`` > 0, beams without a return (+inf, or at/after ``max_range_m``)
    give ``misses`` at that range: the sensor would have seen anything closer. NaN and
    readings below ``min_range_m`` say nothing and give neither.

    The beams' cosines and sines are numpy's; the rest is one compiled pass
    (``_scan_kernel``) in the arithmetic and order of the numpy steps it replaced (the
    returns, the gap allowed between neighbours, ``thin_by_spacing``, the field of view), so
    the points, normals and misses are the same to the bit (``tests/test_slam_scan_points.py``).
    """
    r = _writable(np.ascontiguousarray(ranges_m, dtype=np.float64))
    a = _writable(np.ascontiguousarray(angles_rad, dtype=np.float64))
    if r.shape != a.shape or r.ndim != 1:
        raise ScanError(f"ranges {r.shape} and angles {a.shape} must be equal 1-D arrays")
    with np.errstate(invalid="ignore"):
        cos, sin = np.cos(a), np.sin(a)
    pts, rv, gap, keep, misses, fov, heading = _scan_kernel(
        r, a, cos, sin, float(min_range_m), float(max_range_m), float(no_return_free_m),
        float(min_spacing_m), int(normal_window), float(normal_max_gap_m))
    normals = _normals(pts, int(normal_window), gap, keep)
    return ScanPoints(pts[keep], normals, rv[keep], pts, misses, fov, heading)


@njit_cached
def _scan_kernel(r: F64, a: F64, cos: F64, sin: F64, min_range: float, max_range: float,
                 free_m: float, spacing: float, window: int, max_gap: float
                 ) -> tuple[F64, F64, F64, NDArray[np.int64], F64, float, float]:
    """The returns' points and ranges, the gap allowed at each, the indices kept at
    ``spacing``, the misses at ``free_m``, and the field of view with its middle."""
    N = len(r)
    n = 0
    k = 0
    for i in range(N):
        if not math.isfinite(a[i]):
            continue
        ri = r[i]
        if math.isfinite(ri) and ri >= min_range and ri < max_range:
            n += 1
        elif free_m > 0 and (ri == math.inf or (math.isfinite(ri) and ri >= max_range)):
            k += 1
    pts = np.empty((n, 2))
    rv = np.empty(n)
    first, last = 0.0, 0.0
    misses = np.empty((k, 2))
    n = 0
    k = 0
    finite = 0
    for i in range(N):
        if not math.isfinite(a[i]):
            continue
        if finite == 0:
            first = a[i]
        last = a[i]
        finite += 1
        ri = r[i]
        if math.isfinite(ri) and ri >= min_range and ri < max_range:
            rv[n] = ri
            pts[n, 0], pts[n, 1] = ri * cos[i], ri * sin[i]
            n += 1
        elif free_m > 0 and (ri == math.inf or (math.isfinite(ri) and ri >= max_range)):
            misses[k, 0], misses[k, 1] = free_m * cos[i], free_m * sin[i]
            k += 1
    # the gap allowed between neighbours grows with range, as the beams spread apart
    step = 0.0
    if n > 1:
        first_r, last_r = -1, -1
        for i in range(N):
            ri = r[i]
            if math.isfinite(a[i]) and math.isfinite(ri) and ri >= min_range and ri < max_range:
                if first_r < 0:
                    first_r = i
                last_r = i
        step = abs(a[last_r] - a[first_r]) / (n - 1)
    grow = 2.5 * window * step
    gap = np.empty(n)
    for i in range(n):
        g = grow * rv[i]
        gap[i] = g if g > max_gap else max_gap
    # thin_by_spacing's bins: a point is kept where the path length along the scan (each
    # step at most ``spacing``) crosses a multiple of ``spacing``
    keep = np.empty(n, np.int64)
    m = 0
    if n > 0 and spacing > 0:
        keep[0] = 0
        m = 1
        s = 0.0
        prev = 0.0
        for i in range(1, n):
            d = math.hypot(pts[i, 0] - pts[i - 1, 0], pts[i, 1] - pts[i - 1, 1])
            s += d if d < spacing else spacing
            b = math.floor(s / spacing)
            if b != prev:
                keep[m] = i
                m += 1
            prev = b
    else:
        for i in range(n):
            keep[i] = i
        m = n
    fov, heading = 0.0, 0.0
    if finite >= 2:
        inc = abs(last - first) / (finite - 1)
        fov = min(abs(last - first) + inc, 2 * math.pi)
        heading = 0.5 * (first + last)
    elif finite == 1:
        heading = first
    return pts, rv, gap, keep[:m], misses, fov, heading


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
scan_to_points(np.array([1.0, np.inf, 2.0]), np.array([-0.1, 0.0, 0.1]), 0.1, 10.0,
               min_spacing_m=0.05, no_return_free_m=3.0)
