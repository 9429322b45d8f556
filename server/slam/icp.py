"""Point-to-line ICP in 2D (Gauss–Newton with a Cauchy kernel), its information matrix and a
degeneracy test.

For a scan point p_i (sensor frame) and its nearest map point q_i with normal n_i, the residual
at the pose T = (t, θ) is r_i = n_iᵀ (R(θ) p_i + t − q_i) and its Jacobian
J_i = [n_x, n_y, n_iᵀ R(θ + π/2) p_i]. Each step solves (Σ w_i J_iᵀ J_i) δ = −Σ w_i J_iᵀ r_i with
Cauchy weights w_i = 1 / (1 + (r_i / c)²).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from server.slam.geometry import wrap_angle

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


class PointMap:
    """Map points (N, 2) with unit normals (N, 2) in one frame, indexed for nearest neighbours."""

    def __init__(self, points: F64, normals: F64) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.normals = np.ascontiguousarray(normals, dtype=np.float64)
        self.tree = cKDTree(self.points, leafsize=16, balanced_tree=False, compact_nodes=False)

    def __len__(self) -> int:
        return len(self.points)


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


def _apply(T: F64, pts: F64) -> tuple[F64, F64]:
    c, s = np.cos(T[2]), np.sin(T[2])
    rx = c * pts[:, 0] - s * pts[:, 1]
    ry = s * pts[:, 0] + c * pts[:, 1]
    return rx, ry


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


def icp(scan_points: F64, scan_normals: F64, target: PointMap, T_init: F64,
        p: IcpParams) -> MatchResult:
    """Align ``scan_points`` (sensor frame) to ``target`` starting from ``T_init``."""
    T = np.array(T_init, dtype=np.float64)
    pts = scan_points
    n_pts = len(pts)
    use_normals = scan_normals is not None and np.isfinite(scan_normals).all()
    H = np.zeros((3, 3))
    converged = False
    it = 0
    r = np.zeros(0)
    w = np.zeros(0)
    for it in range(1, p.max_iterations + 1):
        d_max = max(p.min_correspondence_m, p.max_correspondence_m * 0.6 ** (it - 1))
        rx, ry = _apply(T, pts)
        qx, qy = rx + T[0], ry + T[1]
        dist, idx = target.tree.query(np.column_stack([qx, qy]), k=1, distance_upper_bound=d_max)
        ok = np.isfinite(dist)
        if use_normals:
            n_scan = _apply(np.array([0.0, 0.0, T[2]]), scan_normals)
            idx_c = np.minimum(idx, len(target) - 1)
            cosang = n_scan[0] * target.normals[idx_c, 0] + n_scan[1] * target.normals[idx_c, 1]
            ok &= cosang >= p.min_normal_cos
        if ok.sum() < 6:
            break
        i = idx[ok]
        nx, ny = target.normals[i, 0], target.normals[i, 1]
        ex, ey = qx[ok] - target.points[i, 0], qy[ok] - target.points[i, 1]
        r = nx * ex + ny * ey
        jt = -nx * ry[ok] + ny * rx[ok]  # n · (R(θ+π/2) p)
        w = 1.0 / (1.0 + (r / p.kernel_m) ** 2)
        J = np.stack([nx, ny, jt], axis=1)
        Jw = J * w[:, None]
        H = Jw.T @ J
        g = Jw.T @ r
        damp = 1e-9 * np.trace(H) + 1e-12
        try:
            delta = -np.linalg.solve(H + damp * np.eye(3), g)
        except np.linalg.LinAlgError:
            break
        T[0] += delta[0]
        T[1] += delta[1]
        T[2] = float(wrap_angle(T[2] + delta[2]))
        if abs(delta[0]) + abs(delta[1]) < 1e-5 and abs(delta[2]) < 1e-5 and \
                d_max <= p.min_correspondence_m:
            converged = True
            break
    if len(r) == 0:
        return MatchResult(T, np.zeros((3, 3)), float("inf"), 0.0, it, False, None)
    dof = max(float(w.sum()) - 3.0, 1.0)
    sigma2 = max(float((w * r * r).sum()) / dof, 1e-6)
    info = H / sigma2
    inliers = int((np.abs(r) < p.inlier_m).sum())
    rms = float(np.sqrt((w * r * r).sum() / max(w.sum(), 1e-9)))
    degenerate = translation_degeneracy(H, p.degenerate_eigen_ratio)
    return MatchResult(T, info, rms, inliers / max(n_pts, 1), it, converged, degenerate)
