"""Point-to-line ICP's loop, compiled (numba): the steps of ``server.slam.icp.icp``, without
Python between them.

Nearest neighbours come from a uniform grid over the map's points (cells as wide as the
largest correspondence distance, so a point's neighbours within it lie in the 3 × 3 cells
around it) instead of a KD-tree: at a few thousand map points and a few hundred scan points
that is the cheaper search, and the same nearest point is found (exact distances, the first of
equals by index). The arithmetic is ``icp``'s; sums run in another order than numpy's, so a
pose agrees with the numpy loop's to rounding, not bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: the grid's cell side [m]: at least the largest correspondence distance
CELL_M = 0.5


@njit_cached
def build_grid(px: F64, py: F64, cell_m: float) -> tuple[float, float, int, int, I64, I64]:
    """Points bucketed by cell: origin, columns, rows, each cell's first index into
    ``order`` (cells + 1 of them) and ``order`` (point indices, by cell, ascending within)."""
    n = len(px)
    if n == 0:
        return 0.0, 0.0, 1, 1, np.zeros(2, np.int64), np.zeros(0, np.int64)
    x0, y0 = px.min() - cell_m, py.min() - cell_m
    nx = int((px.max() - x0) / cell_m) + 2
    ny = int((py.max() - y0) / cell_m) + 2
    cell = np.empty(n, np.int64)
    start = np.zeros(nx * ny + 1, np.int64)
    for i in range(n):
        c = int((py[i] - y0) / cell_m) * nx + int((px[i] - x0) / cell_m)
        cell[i] = c
        start[c + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return x0, y0, nx, ny, start, order


@njit_cached
def _nearest(qx: float, qy: float, d_max: float, px: F64, py: F64, x0: float, y0: float,
             nx: int, ny: int, start: I64, order: I64, cell_m: float) -> int:
    """The index of the map point nearest (qx, qy) closer than ``d_max``, or -1."""
    fx, fy = (qx - x0) / cell_m, (qy - y0) / cell_m
    if not (fx > -1.0 - d_max / cell_m and fy > -1.0 - d_max / cell_m
            and fx < nx + 1.0 + d_max / cell_m and fy < ny + 1.0 + d_max / cell_m):
        return -1
    cx, cy = math.floor(fx), math.floor(fy)
    reach = max(1, math.ceil(d_max / cell_m))
    best, best_d2 = -1, d_max * d_max
    for gy in range(max(cy - reach, 0), min(cy + reach + 1, ny)):
        for gx in range(max(cx - reach, 0), min(cx + reach + 1, nx)):
            c = gy * nx + gx
            for k in range(start[c], start[c + 1]):
                i = order[k]
                dx, dy = px[i] - qx, py[i] - qy
                d2 = dx * dx + dy * dy
                if d2 < best_d2 or (d2 == best_d2 and best >= 0 and i < best):
                    best, best_d2 = i, d2
    return best


@njit_cached
def _wrap(a: float) -> float:
    """(−π, π], bit for bit as ``schemas.se2.wrap_angle`` (``math.remainder``, which numba
    lacks: ``fmod`` is exact, and so is the one correction, by Sterbenz's lemma)."""
    two_pi = 2.0 * math.pi
    r = np.fmod(a, two_pi)
    if r > math.pi:
        r -= two_pi
    elif r < -math.pi:
        r += two_pi
    return math.pi if r == -math.pi else r


@njit_cached
def _solve3(H: F64, g0: float, g1: float, g2: float, out: F64) -> bool:
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    e, f, i = H[1, 1], H[1, 2], H[2, 2]
    damp = 1e-9 * (a + e + i) + 1e-12
    a, e, i = a + damp, e + damp, i + damp
    A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * A + b * B + c * C
    if not det > 0.0:
        return False
    E, F, I_ = a * i - c * c, b * c - a * f, a * e - b * b
    out[0] = (A * g0 + B * g1 + C * g2) / det
    out[1] = (B * g0 + E * g1 + F * g2) / det
    out[2] = (C * g0 + F * g1 + I_ * g2) / det
    return True


@njit_cached
def icp_loop(sx: F64, sy: F64, snx: F64, sny: F64, have_normals: bool,
             px: F64, py: F64, pnx: F64, pny: F64, grid_x0: float, grid_y0: float,
             grid_nx: int, grid_ny: int, grid_start: I64, grid_order: I64,
             T0: F64, prior: F64, use_prior: bool, params: F64, coarse: bool
             ) -> tuple[F64, F64, float, float, int, int, bool, int]:
    """The Gauss–Newton loop of ``icp``. ``params``: max_iterations, max_correspondence_m,
    min_correspondence_m, kernel_m, min_normal_cos, inlier_m, converged_m, converged_rad,
    point_sigma_m. Returns the pose, H of the last step, Σw r², Σw, inliers, iterations,
    converged, and the last step's correspondences (0: none)."""
    max_it, d_max, d_min = int(params[0]), params[1], params[2]
    kernel, min_cos, inlier_m = params[3], params[4], params[5]
    tol_m, tol_rad, sigma = params[6], params[7], params[8]
    inv_var = 1.0 / sigma ** 2
    inv_kernel = 1.0 / kernel
    tx, ty, th = T0[0], T0[1], T0[2]
    n = len(sx)
    H = np.zeros((3, 3))
    delta = np.zeros(3)
    prev = np.zeros(3)
    wr2 = sw = 0.0
    inliers = 0
    used = 0
    converged = False
    it = 0
    for step in range(1, max_it + 1):
        it = step
        every = 2 if (coarse and d_max > d_min) else 1
        c, s = math.cos(th), math.sin(th)
        h00 = h01 = h02 = h11 = h12 = h22 = g0 = g1 = g2 = 0.0
        wr2_s = sw_s = 0.0
        inl = 0
        m = 0
        for j in range(0, n, every):
            rx, ry = c * sx[j] - s * sy[j], s * sx[j] + c * sy[j]
            qx, qy = rx + tx, ry + ty
            k = _nearest(qx, qy, d_max, px, py, grid_x0, grid_y0, grid_nx, grid_ny,
                         grid_start, grid_order, CELL_M)
            if k < 0:
                continue
            nx_, ny_ = pnx[k], pny[k]
            # the scan point's own normal (where it has one), turned, against the map's
            if have_normals and not math.isnan(snx[j]) and \
                    (c * snx[j] - s * sny[j]) * nx_ + (s * snx[j] + c * sny[j]) * ny_ < min_cos:
                continue
            r = (qx - px[k]) * nx_ + (qy - py[k]) * ny_
            j0, j1, j2 = nx_, ny_, rx * ny_ - ry * nx_
            w = 1.0 / (1.0 + (r * inv_kernel) ** 2)
            h00 += w * j0 * j0
            h01 += w * j0 * j1
            h02 += w * j0 * j2
            h11 += w * j1 * j1
            h12 += w * j1 * j2
            h22 += w * j2 * j2
            g0 += w * j0 * r
            g1 += w * j1 * r
            g2 += w * j2 * r
            wr2_s += w * r * r
            sw_s += w
            if abs(r) < inlier_m:
                inl += 1
            m += 1
        if m < 6:
            break
        H[0, 0], H[0, 1], H[0, 2] = h00, h01, h02
        H[1, 0], H[1, 1], H[1, 2] = h01, h11, h12
        H[2, 0], H[2, 1], H[2, 2] = h02, h12, h22
        wr2, sw, inliers, used = wr2_s, sw_s, inl, m
        if use_prior:
            e0, e1, e2 = tx - prior[0], ty - prior[1], _wrap(th - prior[2])
            Hp = H * inv_var + prior[3:].reshape(3, 3)
            Pm = prior[3:].reshape(3, 3)
            ok = _solve3(Hp, g0 * inv_var + Pm[0, 0] * e0 + Pm[0, 1] * e1 + Pm[0, 2] * e2,
                         g1 * inv_var + Pm[1, 0] * e0 + Pm[1, 1] * e1 + Pm[1, 2] * e2,
                         g2 * inv_var + Pm[2, 0] * e0 + Pm[2, 1] * e1 + Pm[2, 2] * e2, delta)
        else:
            ok = _solve3(H, g0, g1, g2, delta)
        if not ok:
            break
        tx -= delta[0]
        ty -= delta[1]
        th = _wrap(th - delta[2])
        if d_max <= d_min:
            small = abs(delta[0]) + abs(delta[1]) < tol_m and abs(delta[2]) < tol_rad
            flip = (abs(delta[0] + prev[0]) + abs(delta[1] + prev[1]) < 0.2 * tol_m
                    and abs(delta[2] + prev[2]) < 0.2 * tol_rad)
            if flip:
                tx += 0.5 * delta[0]
                ty += 0.5 * delta[1]
                th = _wrap(th + 0.5 * delta[2])
            if small or flip:
                converged = True
                break
        prev[:] = delta
        d_max = max(d_min, 0.5 * d_max)
    return (np.array([tx, ty, th]), H, wr2, sw, inliers, it, converged, used)
