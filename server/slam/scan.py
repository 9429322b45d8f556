"""From ranges to points with normals, in the sensor frame.

Normals come from the scan's own order: a line fitted to the valid neighbours within a few beams
(principal axis of their 2×2 covariance). Neighbours across a range discontinuity are excluded,
so normals are not smeared over corners or depth jumps. A 2D normal is what point-to-line
matching needs; estimators that treat the scan as a 3D cloud return the useless z axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class ScanError(ValueError):
    """A scan cannot be used (shapes differ, no finite beams...)."""

    user_error = True


@dataclass(frozen=True, slots=True)
class ScanPoints:
    """Valid returns of one scan in the sensor frame.

    ``points`` (N, 2) [m]; ``normals`` (N, 2) unit vectors facing the sensor, NaN where no line
    could be fitted; ``ranges_m`` (N,) range of each point.
    """

    points: F64
    normals: F64
    ranges_m: F64

    def __len__(self) -> int:
        return len(self.points)

    def with_normals(self) -> ScanPoints:
        ok = np.isfinite(self.normals[:, 0])
        return ScanPoints(self.points[ok], self.normals[ok], self.ranges_m[ok])


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


def line_normals(points: F64, window: int, max_gap_m: F64 | float) -> F64:
    """Unit normals (N, 2) of ordered points from a line fit over ±``window`` neighbours.

    For neighbours q_j within ``max_gap_m`` (scalar or per point) of p_i, chained along the
    scan, the normal is
    the eigenvector of the smallest eigenvalue of C = Σ (q_j − q̄)(q_j − q̄)ᵀ. NaN where fewer
    than 3 points are usable or the fit is not line-like (λ_min > 0.2 λ_max).
    """
    n = len(points)
    out = np.full((n, 2), np.nan)
    if n < 3:
        return out
    w = window
    pad = np.full((w, 2), np.nan)
    padded = np.concatenate([pad, points, pad])
    win = sliding_window_view(padded, (2 * w + 1, 2))[:, 0]  # (N, 2w+1, 2)
    d = np.linalg.norm(win - points[:, None, :], axis=2)
    ok = d <= np.broadcast_to(np.asarray(max_gap_m, dtype=np.float64), (n,))[:, None]
    # a gap breaks the chain: points beyond a break on either side are excluded
    centre = w
    for k in range(1, w + 1):
        ok[:, centre + k] &= ok[:, centre + k - 1]
        ok[:, centre - k] &= ok[:, centre - k + 1]
    cnt = ok.sum(axis=1)
    wx = np.where(ok, win[..., 0], 0.0)
    wy = np.where(ok, win[..., 1], 0.0)
    safe = np.maximum(cnt, 1)
    mx, my = wx.sum(1) / safe, wy.sum(1) / safe
    dx = np.where(ok, win[..., 0] - mx[:, None], 0.0)
    dy = np.where(ok, win[..., 1] - my[:, None], 0.0)
    sxx, syy, sxy = (dx * dx).sum(1), (dy * dy).sum(1), (dx * dy).sum(1)
    # smallest eigenvalue/vector of [[sxx, sxy], [sxy, syy]] in closed form
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
    lmin, lmax = tr / 2 - disc, tr / 2 + disc
    # principal (line) direction = eigenvector of lmax; the normal is perpendicular to it
    ux, uy = sxy, lmax - sxx
    alt = np.abs(ux) + np.abs(uy) < 1e-12
    ux = np.where(alt, lmax - syy, ux)
    uy = np.where(alt, sxy, uy)
    norm = np.hypot(ux, uy)
    good = (cnt >= 3) & (norm > 1e-12) & (lmin <= 0.2 * lmax)
    nx, ny = -uy / np.where(norm > 0, norm, 1.0), ux / np.where(norm > 0, norm, 1.0)
    # face the sensor: n · p < 0
    flip = nx * points[:, 0] + ny * points[:, 1] > 0
    nx, ny = np.where(flip, -nx, nx), np.where(flip, -ny, ny)
    out[good, 0] = nx[good]
    out[good, 1] = ny[good]
    return out


def thin_by_spacing(points: F64, spacing_m: float) -> NDArray[np.bool_]:
    """Keep-mask dropping ordered points closer than ``spacing_m`` to the last kept one.

    Approximated in one pass: a point is kept when the path length since the previous kept
    point (cumulative along the scan) crosses a multiple of ``spacing_m``.
    """
    n = len(points)
    if n == 0 or spacing_m <= 0:
        return np.ones(n, dtype=bool)
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    step = np.minimum(step, spacing_m)  # a jump always starts a new bin
    s = np.concatenate([[0.0], np.cumsum(step)])
    bins = np.floor(s / spacing_m).astype(np.int64)
    keep = np.ones(n, dtype=bool)
    keep[1:] = bins[1:] != bins[:-1]
    return keep


def scan_to_points(ranges_m: F64, angles_rad: F64, min_range_m: float, max_range_m: float,
                   normal_window: int = 2, normal_max_gap_m: float = 0.3,
                   min_spacing_m: float = 0.0) -> ScanPoints:
    """Points (sensor frame) and normals of the beams with a return, thinned to a spacing."""
    r, a = valid_returns(ranges_m, angles_rad, min_range_m, max_range_m)
    pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    # the gap allowed between neighbours grows with range, as the beams spread apart
    beam_step = float(np.median(np.abs(np.diff(a)))) if len(a) > 1 else 0.0
    gap = np.maximum(normal_max_gap_m, 2.5 * normal_window * beam_step * r)
    normals = line_normals(pts, normal_window, gap)
    keep = thin_by_spacing(pts, min_spacing_m)
    return ScanPoints(pts[keep], normals[keep], r[keep])
