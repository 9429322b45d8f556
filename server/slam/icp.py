"""Point-to-line ICP in 2D (Gauss–Newton with a Cauchy kernel), its information matrix and a
degeneracy test.

For a scan point p_i (sensor frame) and its nearest map point q_i with normal n_i, the residual
at the pose T = (t, θ) is r_i = n_iᵀ (R(θ) p_i + t − q_i) and its Jacobian
J_i = [n_x, n_y, n_iᵀ R(θ + π/2) p_i]. Each step solves (Σ w_i J_iᵀ J_i) δ = −Σ w_i J_iᵀ r_i with
Cauchy weights w_i = 1 / (1 + (r_i / c)²).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from schemas.se2 import wrap_angle

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class IcpParams:
    max_iterations: int = 25
    max_correspondence_m: float = 0.5
    min_correspondence_m: float = 0.15
    kernel_m: float = 0.05
    min_normal_cos: float = 0.6
    inlier_m: float = 0.1
    degenerate_eigen_ratio: float = 0.02
    converged_m: float = 5e-4
    point_sigma_m: float = 0.03
    min_points_coarse: int = 20
    converged_rad: float = 5e-4


class PointMap:
    """Map points (N, 2) with unit normals (N, 2) in one frame, indexed for nearest neighbours.

    Also kept as complex numbers x + iy (rotation is one multiplication), with a sentinel row
    at index N: the KD-tree reports N for "no neighbour within the radius".
    """

    def __init__(self, points: F64, normals: F64) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        self.normals = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 2)
        self.tree = cKDTree(self.points, leafsize=16, balanced_tree=False, compact_nodes=False)
        self.points_c = np.append(self.points[:, 0] + 1j * self.points[:, 1], 0.0)
        self.normals_c = np.append(self.normals[:, 0] + 1j * self.normals[:, 1], 0.0)

    def __len__(self) -> int:
        return len(self.points)

    def __getstate__(self) -> dict[str, F64]:
        return {"points": self.points, "normals": self.normals}   # the rest is rebuilt

    def __setstate__(self, state: dict[str, F64]) -> None:
        self.__init__(state["points"], state["normals"])  # type: ignore[misc]


@dataclass(frozen=True)
class MatchResult:
    """Outcome of matching a scan against a map.

    ``T_map_scan`` (x, y, θ); ``information`` (3×3) = Σ w JᵀJ / σ̂² in (x [m], y [m], θ [rad]);
    ``degenerate_dir`` is the unit map-frame direction along which translation is unobservable
    (or None); ``inlier_fraction`` counts scan points within ``inlier_m`` of the map's lines.
    """

    T_map_scan: F64
    information: F64
    rms_m: float
    inlier_fraction: float
    iterations: int
    converged: bool
    degenerate_dir: F64 | None

    @property
    def degenerate(self) -> bool:
        return self.degenerate_dir is not None


def translation_degeneracy(information: F64, ratio: float) -> F64 | None:
    """Unit direction of weakest translation information if λ_min/λ_max < ``ratio``, else None.

    Uses the Schur complement H_tt − H_tθ H_θθ⁻¹ H_θt (translation information when the angle
    is also estimated).
    """
    H = information
    Htt = H[:2, :2] - np.outer(H[:2, 2], H[2, :2]) / H[2, 2] if H[2, 2] > 0 else H[:2, :2]
    w, v = np.linalg.eigh(Htt)
    if w[1] <= 0 or w[0] < ratio * w[1]:
        return np.asarray(v[:, 0], dtype=np.float64)
    return None


def _solve3(H: F64, g: F64) -> tuple[float, float, float] | None:
    """Solve the 3×3 system H δ = g (symmetric positive semi-definite) by Cramer's rule."""
    a, b, c = float(H[0, 0]), float(H[0, 1]), float(H[0, 2])
    e, f, i = float(H[1, 1]), float(H[1, 2]), float(H[2, 2])
    damp = 1e-9 * (a + e + i) + 1e-12  # keeps unobservable directions at the guess
    a, e, i = a + damp, e + damp, i + damp
    A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * A + b * B + c * C
    if not det > 0.0:
        return None
    g0, g1, g2 = float(g[0]), float(g[1]), float(g[2])
    E, F, I_ = a * i - c * c, b * c - a * f, a * e - b * b
    return ((A * g0 + B * g1 + C * g2) / det, (B * g0 + E * g1 + F * g2) / det,
            (C * g0 + F * g1 + I_ * g2) / det)


def icp(scan_points: F64, scan_normals: F64 | None, target: PointMap, T_init: F64,
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
    M, MN = target.points_c, target.normals_c
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
        dist, idx = target.tree.query(Q.view(np.float64).reshape(-1, 2), k=1,
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
