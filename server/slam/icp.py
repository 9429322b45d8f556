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
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from server.slam.icp_kernel import CELL_M, build_grid, icp_loop

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

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
        # the columns the compiled loop reads, and its grid of the points by cell
        self._xy = (np.ascontiguousarray(self.points[:, 0]),
                    np.ascontiguousarray(self.points[:, 1]),
                    np.ascontiguousarray(self.normals[:, 0]),
                    np.ascontiguousarray(self.normals[:, 1]))
        self.grid = build_grid(self._xy[0], self._xy[1], CELL_M)
        self._tree: cKDTree | None = None

    @property
    def tree(self) -> cKDTree:
        """A KD-tree of the points, for callers that query it themselves (built at first use:
        matching does not need it)."""
        if self._tree is None:
            from scipy.spatial import cKDTree  # not loaded where nothing asks (slam-log)

            self._tree = cKDTree(self.points, leafsize=16, balanced_tree=False,
                                 compact_nodes=False)
        return self._tree

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
    n_pts = len(scan_points)
    pts = np.asarray(scan_points, dtype=np.float64)
    if scan_normals is not None:
        nrm = np.asarray(scan_normals, dtype=np.float64)
        snx, sny = np.ascontiguousarray(nrm[:, 0]), np.ascontiguousarray(nrm[:, 1])
    else:
        snx = sny = np.zeros(n_pts)
    prior = np.zeros(12)
    if prior_info is not None:
        prior[:3] = np.asarray(T_init, dtype=np.float64)
        prior[3:] = np.asarray(prior_info, dtype=np.float64).ravel()
    params = np.array([p.max_iterations, p.max_correspondence_m, p.min_correspondence_m,
                       p.kernel_m, p.min_normal_cos, p.inlier_m, p.converged_m,
                       p.converged_rad, p.point_sigma_m], dtype=np.float64)
    mx, my, mnx, mny = target._xy
    x0, y0, gnx, gny, start, order = target.grid
    # while the search radius still shrinks, every other point is enough to steer the pose
    T, H, wr2, sw, inliers, it, converged, used = icp_loop(
        np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]), snx, sny,
        scan_normals is not None, mx, my, mnx, mny, x0, y0, gnx, gny, start, order,
        np.asarray(T_init, dtype=np.float64), prior, prior_info is not None, params,
        n_pts >= 4 * p.min_points_coarse)
    if used == 0:
        return MatchResult(T, np.zeros((3, 3)), float("inf"), 0.0, it, False, None)
    sigma2 = max(wr2 / max(sw - 3.0, 1.0), 1e-6)
    info = H / sigma2
    rms = math.sqrt(wr2 / max(sw, 1e-9))
    degenerate = translation_degeneracy(H, p.degenerate_eigen_ratio)
    return MatchResult(T, info, rms, inliers / max(n_pts, 1), it, bool(converged), degenerate)


def _warm_up() -> None:
    """Compile the kernels (or load them from numba's cache) now, at import: a first scan
    that waited seconds for the compiler would change what a lockstep run does (scans queued
    or dropped meanwhile), so a fresh install would not repeat a cached one."""
    t = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
    pts = np.column_stack([2.0 * np.cos(t), np.sin(t)])
    icp(pts, -pts / np.linalg.norm(pts, axis=1, keepdims=True), PointMap(pts, -pts),
        np.zeros(3), IcpParams())


_warm_up()
