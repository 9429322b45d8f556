"""Keyframes and the point maps built from them (in the map frame or a keyframe's frame)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from server.slam.geometry import between, rotate_vectors, transform_points
from server.slam.icp import PointMap
from server.slam.scan import ScanPoints

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Keyframe:
    """A scan kept in the graph: key index k, stamp, points/normals in the robot frame, and the
    odometry pose it was taken at."""

    index: int
    stamp_ns: int
    scan: ScanPoints
    T_odom_robot: F64


def gather(keyframes: Sequence[Keyframe], T_frame_kf: F64,
           with_normals: bool = True) -> tuple[F64, F64]:
    """Points (and normals) of keyframes placed by ``T_frame_kf`` (K, 3), concatenated."""
    pts: list[F64] = []
    nrm: list[F64] = []
    for kf, T in zip(keyframes, T_frame_kf, strict=True):
        sc = kf.scan.with_normals() if with_normals else kf.scan
        pts.append(transform_points(T, sc.points))
        nrm.append(rotate_vectors(float(T[2]), sc.normals))
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(pts), np.concatenate(nrm)


def voxel_thin(points: F64, voxel_m: float, *extra: F64) -> tuple[F64, ...]:
    """Keep the first point per ``voxel_m`` cell (and the matching rows of ``extra``)."""
    if len(points) == 0 or voxel_m <= 0:
        return (points, *extra)
    ij = np.floor(points / voxel_m).astype(np.int64)
    key = ij[:, 0] * 1_000_003 + ij[:, 1]
    _, first = np.unique(key, return_index=True)
    first.sort()
    return (points[first], *(e[first] for e in extra))


def local_point_map(keyframes: Sequence[Keyframe], T_map_kf: F64, max_points: int) -> PointMap:
    """Scan-to-map target: the keyframes' points with normals, in the map frame."""
    pts, nrm = gather(keyframes, T_map_kf)
    if len(pts) > max_points:
        # newest keyframes come last; keep them, thin the rest
        pts, nrm = voxel_thin(pts[::-1], 0.02, nrm[::-1])
    return PointMap(pts, nrm)


def points_in_frame(keyframes: Sequence[Keyframe], T_map_kf: F64, T_map_frame: F64,
                    voxel_m: float, max_range_m: float | None = None) -> tuple[F64, F64]:
    """Keyframes' points and normals in the frame ``T_map_frame``, thinned to ``voxel_m``;
    with ``max_range_m``, points farther than that from their own keyframe are dropped."""
    rel = between(T_map_frame, T_map_kf)
    pts: list[F64] = []
    nrm: list[F64] = []
    for kf, T in zip(keyframes, rel, strict=True):
        sc = kf.scan
        keep = np.isfinite(sc.normals[:, 0])
        if max_range_m is not None:
            keep &= sc.ranges_m <= max_range_m
        pts.append(transform_points(T, sc.points[keep]))
        nrm.append(rotate_vectors(float(T[2]), sc.normals[keep]))
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p, n = voxel_thin(np.concatenate(pts), voxel_m, np.concatenate(nrm))
    return p, n
