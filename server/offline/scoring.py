"""Scoring a run against the simulator's ground truth (pure numpy, no I/O).

It scores the server's estimates (trajectories and its nav2 grid), so it sits beside
``server.offline.evaluation`` and needs what the server has (scipy); the truth arrives as plain
arrays.

Frames: a robot's estimates live in its team's map frame. The map frame is tied to the world
by the first scan of the team's anchor robot: ``T_world_map = x_true(t0) ⊕ x_est(t0)⁻¹``.
Nothing is fitted, so the errors include every bit of drift (as in the dissertation's plots).
The ATE RMSE is the exception: it is computed after the least-squares SE(2) alignment of the
final (optimised) trajectory, the usual definition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from schemas.occupancy import FREE, FREE_BELOW, OCCUPIED, OCCUPIED_ABOVE, UNKNOWN
from schemas.se2 import F64, compose, inverse, transform_points, wrap_angle


def anchor_transform(true_first: ArrayLike, est_first: ArrayLike) -> F64:
    """T_world_map from one pose known in both frames."""
    return compose(true_first, inverse(est_first))


@dataclass(frozen=True)
class PoseErrors:
    stamps_ns: NDArray[np.int64]
    position_m: F64
    yaw_rad: F64

    @property
    def max_position_m(self) -> float:
        return float(self.position_m.max()) if len(self.position_m) else float("nan")

    @property
    def max_yaw_rad(self) -> float:
        return float(np.abs(self.yaw_rad).max()) if len(self.yaw_rad) else float("nan")


def match_truth(stamps_ns: ArrayLike, truth_stamps_ns: ArrayLike, truth_poses: ArrayLike,
                tolerance_ns: int = 1_000_000) -> tuple[NDArray[np.int64], F64]:
    """Indices of estimates with a ground-truth pose within ``tolerance_ns``, and those poses."""
    s = np.asarray(stamps_ns, np.int64)
    ts = np.asarray(truth_stamps_ns, np.int64)
    tp = np.asarray(truth_poses, np.float64).reshape(-1, 3)
    if len(ts) == 0 or len(s) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    j = np.clip(np.searchsorted(ts, s), 1, len(ts) - 1) if len(ts) > 1 else np.zeros_like(s)
    if len(ts) > 1:
        j = np.where(np.abs(ts[j - 1] - s) <= np.abs(ts[j] - s), j - 1, j)
    ok = np.abs(ts[j] - s) <= tolerance_ns
    return np.flatnonzero(ok), tp[j[ok]]


def pose_errors(stamps_ns: ArrayLike, est_map: ArrayLike, T_world_map: ArrayLike,
                truth_stamps_ns: ArrayLike, truth_poses: ArrayLike) -> PoseErrors:
    """Per-estimate position [m] and yaw [rad] errors in the world frame."""
    idx, truth = match_truth(stamps_ns, truth_stamps_ns, truth_poses)
    est = compose(T_world_map, np.asarray(est_map, np.float64).reshape(-1, 3)[idx])
    d = est - truth
    return PoseErrors(np.asarray(stamps_ns, np.int64)[idx], np.hypot(d[:, 0], d[:, 1]),
                      wrap_angle(d[:, 2]))


def align_se2(est_xy: ArrayLike, true_xy: ArrayLike) -> F64:
    """Least-squares T (x, y, θ) with T ⊕ est ≈ true for point sets (N, 2) (Umeyama, no scale)."""
    a, b = np.asarray(est_xy, np.float64), np.asarray(true_xy, np.float64)
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    H = (a - ma).T @ (b - mb)
    theta = math.atan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])
    c, s = math.cos(theta), math.sin(theta)
    t = mb - np.array([[c, -s], [s, c]]) @ ma
    return np.array([t[0], t[1], theta])


def ate_rmse(stamps_ns: ArrayLike, est: ArrayLike, truth_stamps_ns: ArrayLike,
             truth_poses: ArrayLike) -> float:
    """Absolute trajectory error [m] after the best SE(2) alignment."""
    idx, truth = match_truth(stamps_ns, truth_stamps_ns, truth_poses)
    if len(idx) < 2:
        return float("nan")
    e = np.asarray(est, np.float64).reshape(-1, 3)[idx]
    T = align_se2(e[:, :2], truth[:, :2])
    aligned = compose(T, e)
    return float(np.sqrt(np.mean(np.sum((aligned[:, :2] - truth[:, :2]) ** 2, axis=1))))


@dataclass(frozen=True)
class MapQuality:
    true_coverage: float      # explored free area inside the true free space / true free area
    explored_free_m2: float
    true_free_m2: float
    phantom_area_m2: float    # marked explored where there is neither free space nor wall


def map_quality(est: ArrayLike, est_resolution_m: float, est_origin_xy: ArrayLike,
                T_world_map: ArrayLike, truth: ArrayLike, truth_resolution_m: float,
                truth_origin_xy: ArrayLike, wall_tolerance_m: float = 0.15) -> MapQuality:
    """Compare an estimated nav2 grid (map frame) with the true grid (world frame, free 0,
    occupied 100, outside -1) by sampling the estimate at every true cell's centre, and every
    estimated cell's centre in the true grid."""
    e, t = np.asarray(est, np.int8), np.asarray(truth, np.int8)
    eo = np.asarray(est_origin_xy, np.float64)
    to = np.asarray(truth_origin_xy, np.float64)
    true_free = t == FREE
    walls = ndimage.binary_dilation(t == OCCUPIED, iterations=max(
        1, round(wall_tolerance_m / truth_resolution_m)))
    # the estimate at each true cell
    rows, cols = np.nonzero(true_free)
    xy_w = np.column_stack([to[0] + (cols + 0.5) * truth_resolution_m,
                            to[1] + (rows + 0.5) * truth_resolution_m])
    xy_m = transform_points(inverse(T_world_map), xy_w)
    v = _sample(e, est_resolution_m, eo, xy_m, UNKNOWN)
    seen_free = (v != UNKNOWN) & (v < FREE_BELOW)
    cell_t = truth_resolution_m ** 2
    true_free_m2 = float(true_free.sum()) * cell_t
    explored = float(seen_free.sum()) * cell_t
    # each estimated known cell in the true grid
    known = (e != UNKNOWN) & ((e < FREE_BELOW) | (e > OCCUPIED_ABOVE))
    r2, c2 = np.nonzero(known)
    xy_e = np.column_stack([eo[0] + (c2 + 0.5) * est_resolution_m,
                            eo[1] + (r2 + 0.5) * est_resolution_m])
    inside = true_free | walls
    w = _sample(inside.astype(np.int8), truth_resolution_m, to,
                transform_points(T_world_map, xy_e), 0)
    phantom = float((w == 0).sum()) * est_resolution_m ** 2
    return MapQuality(explored / true_free_m2 if true_free_m2 else float("nan"), explored,
                      true_free_m2, phantom)


def _sample(grid: NDArray[np.int8], res: float, origin: F64, xy: F64,
            outside: int) -> NDArray[np.int8]:
    col = np.floor((xy[:, 0] - origin[0]) / res).astype(np.int64)
    row = np.floor((xy[:, 1] - origin[1]) / res).astype(np.int64)
    ok = (row >= 0) & (row < grid.shape[0]) & (col >= 0) & (col < grid.shape[1])
    out = np.full(len(xy), outside, np.int8)
    out[ok] = grid[row[ok], col[ok]]
    return out
