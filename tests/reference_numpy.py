"""The numpy loops that compiled ones replaced, kept as the references their results are
checked against: ICP and a scan's normals (``tests/test_slam_icp.py``), and a scan's points
(``tests/test_slam_scan_points.py``)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from schemas.se2 import wrap_angle
from server.slam.icp import IcpParams, MatchResult, PointMap, _solve3, translation_degeneracy
from server.slam.scan import ScanPoints, field_of_view, line_normals, thin_by_spacing, valid_returns

F64 = NDArray[np.float64]


def reference_icp(scan_points: F64, scan_normals: F64 | None, target: PointMap, T_init: F64,
        p: IcpParams, prior_info: F64 | None = None) -> MatchResult:
    """Align ``scan_points`` (sensor frame) to ``target`` starting from ``T_init``.

    Correspondences are searched within a radius shrinking from ``max_correspondence_m`` to
    ``min_correspondence_m``; a scan point whose own normal (where known) disagrees with the
    map normal by more than acos(``min_normal_cos``) is not paired.

    With ``prior_info`` Λ (3×3), the pose minimises Σ w_i r_i² / σ_p² + (x − x₀)ᵀ Λ (x − x₀)
    with x₀ = ``T_init`` and σ_p = ``point_sigma_m``: directions the scan does not constrain
    (a corridor's axis) stay with the prediction instead of drifting.
    """
    prior_T = np.asarray(T_init, dtype=np.float64)
    inv_var = 1.0 / p.point_sigma_m ** 2
    tx, ty, th = (float(v) for v in T_init)
    n_pts = len(scan_points)
    # complex arithmetic: R(θ)p = p·e^{iθ}; n·v = Re(v·conj(n)); n·(R(θ+π/2)p) = −Im(Rp·conj(n))
    P_all = scan_points[:, 0] + 1j * scan_points[:, 1]
    have_n = scan_normals is not None
    Ns_all = np.zeros(n_pts, dtype=np.complex128)
    free_all = np.ones(n_pts, dtype=bool)
    if scan_normals is not None:
        Ns_all = np.nan_to_num(scan_normals[:, 0]) + 1j * np.nan_to_num(scan_normals[:, 1])
        free_all = ~np.isfinite(scan_normals[:, 0])
    # while the search radius still shrinks, every other point is enough to steer the pose
    coarse = (P_all[::2], Ns_all[::2], free_all[::2]) if n_pts >= 4 * p.min_points_coarse else \
        (P_all, Ns_all, free_all)
    M, MN = _complex(target)
    H = np.zeros((3, 3))
    converged = False
    it = 0
    r = np.zeros(0)
    w = np.zeros(0)
    d_max = p.max_correspondence_m
    prev = (0.0, 0.0, 0.0)
    inv_kernel = 1.0 / p.kernel_m
    for step in range(1, p.max_iterations + 1):
        it = step
        P, Ns, no_normal = coarse if d_max > p.min_correspondence_m else (P_all, Ns_all, free_all)
        rot = complex(math.cos(th), math.sin(th))
        RP = P * rot
        Q = RP + complex(tx, ty)
        dist, idx = _tree(target).query(Q.view(np.float64).reshape(-1, 2), k=1,
                                      distance_upper_bound=d_max)
        ok = dist < d_max
        nc = MN[idx].conj()
        if have_n:
            ok &= ((Ns * rot * nc).real >= p.min_normal_cos) | no_normal
        sel = np.flatnonzero(ok)
        if len(sel) < 6:
            break
        nc = nc[sel]
        r = ((Q[sel] - M[idx[sel]]) * nc).real
        J = np.empty((3, len(sel)))
        J[0] = nc.real
        J[1] = -nc.imag
        J[2] = -(RP[sel] * nc).imag
        w = 1.0 / (1.0 + (r * inv_kernel) ** 2)
        Jw = J * w
        H = Jw @ J.T
        g = Jw @ r
        if prior_info is not None:
            # MAP step: (H/σ² + Λ) δ = g/σ² + Λ (x − x_prior)
            e = np.array([tx - prior_T[0], ty - prior_T[1],
                          wrap_angle(th - prior_T[2])])
            delta = _solve3(H * inv_var + prior_info, g * inv_var + prior_info @ e)
        else:
            delta = _solve3(H, g)
        if delta is None:
            break
        tx -= delta[0]
        ty -= delta[1]
        th = wrap_angle(th - delta[2])
        if d_max <= p.min_correspondence_m:
            tol_m, tol_rad = p.converged_m, p.converged_rad
            small = abs(delta[0]) + abs(delta[1]) < tol_m and abs(delta[2]) < tol_rad
            # correspondences flipping between two sets make the steps alternate: stop midway
            flip = (abs(delta[0] + prev[0]) + abs(delta[1] + prev[1]) < 0.2 * tol_m
                    and abs(delta[2] + prev[2]) < 0.2 * tol_rad)
            if flip:
                tx += 0.5 * delta[0]
                ty += 0.5 * delta[1]
                th = wrap_angle(th + 0.5 * delta[2])
            if small or flip:
                converged = True
                break
        prev = delta
        d_max = max(p.min_correspondence_m, 0.5 * d_max)
    T = np.array([tx, ty, th])
    if len(r) == 0:
        return MatchResult(T, np.zeros((3, 3)), float("inf"), 0.0, it, False, None)
    wr2 = float(w @ (r * r))
    sw = float(w.sum())
    sigma2 = max(wr2 / max(sw - 3.0, 1.0), 1e-6)
    info = H / sigma2
    inliers = int(np.count_nonzero(np.abs(r) < p.inlier_m))
    rms = math.sqrt(wr2 / max(sw, 1e-9))
    degenerate = translation_degeneracy(H, p.degenerate_eigen_ratio)
    return MatchResult(T, info, rms, inliers / max(n_pts, 1), it, converged, degenerate)


def _tree(target: PointMap) -> cKDTree:
    return target.tree


def _complex(target: PointMap) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    pts, nrm = target.points, target.normals
    return (np.append(pts[:, 0] + 1j * pts[:, 1], 0.0),
            np.append(nrm[:, 0] + 1j * nrm[:, 1], 0.0))


def reference_line_normals(points: F64, window: int, max_gap_m: F64 | float,
                 centers: NDArray[np.int64] | None = None) -> F64:
    """Unit normals (M, 2) at ``centers`` (default: all N points) of ordered points, from a
    line fit over up to ±``window`` neighbours.

    Neighbours are taken outwards from the centre while each stays within ``max_gap_m``
    (scalar or per point) of it, so a range jump ends the run. The normal is the eigenvector of
    the smallest eigenvalue of C = Σ (q_j − q̄)(q_j − q̄)ᵀ, facing the sensor (n · p < 0). NaN
    where fewer than 3 points are usable or the fit is not line-like (λ_min > 0.2 λ_max).
    """
    n = len(points)
    idx = np.arange(n) if centers is None else np.asarray(centers, dtype=np.int64)
    m = len(idx)
    out = np.full((m, 2), np.nan)
    if n < 3 or m == 0:
        return out
    gap = np.broadcast_to(np.asarray(max_gap_m, dtype=np.float64), (n,))[idx]
    gap2 = gap * gap
    px, py = points[:, 0], points[:, 1]
    cx, cy = px[idx], py[idx]
    cnt = np.ones(m)
    sx, sy = cx.copy(), cy.copy()
    sxx, syy, sxy = cx * cx, cy * cy, cx * cy
    for sign in (1, -1):
        alive = np.ones(m, dtype=bool)
        for k in range(1, window + 1):
            j = idx + sign * k
            jc = np.clip(j, 0, n - 1)
            qx, qy = px[jc], py[jc]
            alive &= (j == jc) & ((qx - cx) ** 2 + (qy - cy) ** 2 <= gap2)
            a = alive.astype(np.float64)
            cnt += a
            qx, qy = qx * a, qy * a
            sx += qx
            sy += qy
            sxx += qx * qx
            syy += qy * qy
            sxy += qx * qy
    mx, my = sx / cnt, sy / cnt
    cxx, cyy, cxy = sxx / cnt - mx * mx, syy / cnt - my * my, sxy / cnt - mx * my
    # eigen-decomposition of [[cxx, cxy], [cxy, cyy]] in closed form
    tr, det = cxx + cyy, cxx * cyy - cxy * cxy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
    lmin, lmax = tr / 2 - disc, tr / 2 + disc
    # the line direction is the eigenvector of lmax; the normal is perpendicular to it
    ux, uy = cxy, lmax - cxx
    alt = np.abs(ux) + np.abs(uy) < 1e-12
    ux = np.where(alt, lmax - cyy, ux)
    uy = np.where(alt, cxy, uy)
    norm = np.hypot(ux, uy)
    good = (cnt >= 3) & (norm > 1e-12) & (lmin <= 0.2 * lmax)
    safe = np.where(norm > 0, norm, 1.0)
    nx, ny = -uy / safe, ux / safe
    flip = nx * cx + ny * cy > 0
    out[good, 0] = np.where(flip, -nx, nx)[good]
    out[good, 1] = np.where(flip, -ny, ny)[good]
    return out


def reference_scan_to_points(ranges_m: F64, angles_rad: F64, min_range_m: float,
                             max_range_m: float, normal_window: int = 2,
                             normal_max_gap_m: float = 0.3, min_spacing_m: float = 0.0,
                             no_return_free_m: float = 0.0) -> ScanPoints:
    """``server.slam.scan.scan_to_points`` as numpy steps, before its compiled pass."""
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
    beam_step = abs(float(a[-1] - a[0])) / (len(a) - 1) if len(a) > 1 else 0.0
    gap = np.maximum(normal_max_gap_m, 2.5 * normal_window * beam_step * r)
    keep = np.flatnonzero(thin_by_spacing(pts, min_spacing_m))
    normals = line_normals(pts, normal_window, gap, keep)
    return ScanPoints(pts[keep], normals, r[keep], pts, misses, *field_of_view(angles_rad))
