"""Keyframes, the point maps built from them (in the map frame or a keyframe's frame), and
which of them are near a pose."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, wrap_angle
from server.slam.icp import PointMap
from server.slam.render_store import RenderScan
from server.slam.scan import ScanPoints

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class Keyframe:
    """A scan kept in the graph: key index k, stamp, its odometry pose, the points with a
    normal it is matched by (``matchable``, robot frame, double precision) and what only
    drawing the map needs (``render``: every return and the ends of empty beams, single
    precision, on disk by default: ``server.slam.render_store``)."""

    index: int
    stamp_ns: int
    T_odom_robot: F64
    matchable: ScanPoints
    render: RenderScan

    @classmethod
    def create(cls, index: int, stamp_ns: int, scan: ScanPoints, T_odom_robot: F64,
               spill: bool = True, single: bool = False) -> Keyframe:
        """A keyframe of ``scan``, whose arrays become read-only: a keyframe never changes
        (and a snapshot stores read-only arrays once, not again each time). The points
        without a normal are not kept: only the map drew from them, and it draws from
        ``render``. ``single``: the matching points, normals and ranges in single precision
        (half the memory; ``gather`` computes in double precision from them)."""
        ok = np.isfinite(scan.normals[:, 0])
        empty = _frozen(np.zeros((0, 2)))
        keep = _frozen32 if single else _frozen
        matchable = ScanPoints(keep(scan.points[ok]), keep(scan.normals[ok]),
                               keep(scan.ranges_m[ok]), empty, empty, scan.fov_rad,
                               scan.heading_rad)
        return cls(index, stamp_ns, _frozen(T_odom_robot), matchable,
                   RenderScan.of(scan.hits, scan.misses, spill))

    def for_drawing(self) -> Keyframe:
        """This keyframe without its matching points: what drawing the map and the point
        cloud read (``render``), once nothing will be matched against it any more."""
        return Keyframe(self.index, self.stamp_ns, self.T_odom_robot, _NO_POINTS, self.render)

    @property
    def hits(self) -> F32:
        """Every return, robot frame (N, 2)."""
        return self.render.hits

    @property
    def misses(self) -> F32:
        """The ends of beams without a return, robot frame (K, 2)."""
        return self.render.misses


def _frozen(a: F64) -> F64:
    """A read-only copy."""
    b: F64 = np.array(a, dtype=np.float64)
    b.flags.writeable = False
    return b


def _frozen32(a: F64) -> F64:
    """A read-only single-precision copy (typed as the double arrays it stands for: every
    reader computes from it in double precision)."""
    b = np.array(a, dtype=np.float32)
    b.flags.writeable = False
    return cast("F64", b)


_EMPTY = _frozen(np.zeros((0, 2)))
_NO_POINTS = ScanPoints(_EMPTY, _EMPTY, _frozen(np.zeros(0)), _EMPTY, _EMPTY, 0.0, 0.0)


def gather(keyframes: Sequence[Keyframe], T_frame_kf: F64) -> tuple[F64, F64]:
    """Matching points and normals of keyframes placed by ``T_frame_kf`` (K, 3), concatenated
    (only points with a normal)."""
    if len(keyframes) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    parts = [kf.matchable for kf in keyframes]
    counts = [len(p) for p in parts]
    P = np.concatenate([p.points for p in parts])
    N = np.concatenate([p.normals for p in parts])
    T = np.asarray(T_frame_kf, dtype=np.float64).reshape(-1, 3)
    c = np.repeat(np.cos(T[:, 2]), counts)
    s = np.repeat(np.sin(T[:, 2]), counts)
    pts = np.empty(P.shape)        # double precision, whatever the keyframes hold
    pts[:, 0] = c * P[:, 0] - s * P[:, 1] + np.repeat(T[:, 0], counts)
    pts[:, 1] = s * P[:, 0] + c * P[:, 1] + np.repeat(T[:, 1], counts)
    nrm = np.empty(N.shape)
    nrm[:, 0] = c * N[:, 0] - s * N[:, 1]
    nrm[:, 1] = s * N[:, 0] + c * N[:, 1]
    return pts, nrm


def voxel_keys(points: F64, voxel_m: float) -> NDArray[np.int64]:
    """A key per point naming its ``voxel_m`` cell (``voxel_thin``'s)."""
    ij = np.floor(points / voxel_m).astype(np.int64)
    return ij[:, 0] * 1_000_003 + ij[:, 1]


def voxel_thin(points: F64, voxel_m: float, *extra: F64) -> tuple[F64, ...]:
    """Keep the first point per ``voxel_m`` cell (and the matching rows of ``extra``)."""
    if len(points) == 0 or voxel_m <= 0:
        return (points, *extra)
    _, first = np.unique(voxel_keys(points, voxel_m), return_index=True)
    first.sort()
    return (points[first], *(e[first] for e in extra))


def voxel_mean(points: F64, normals: F64, voxel_m: float,
               min_normal_agreement: float = 0.7) -> tuple[F64, F64]:
    """Average points and normals per ``voxel_m`` cell.

    Overlapping scans put many noisy points on each wall; their mean lies on the wall with less
    noise, and point-to-line ICP converges in fewer steps against it. Cells whose normals
    disagree (resultant length below ``min_normal_agreement`` of the count, e.g. both faces of
    a thin wall) are dropped.
    """
    if len(points) == 0:
        return points, normals
    ij = np.floor(points / voxel_m).astype(np.int64)
    key = ij[:, 0] * 4_194_304 + ij[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    n = len(uniq)
    cnt = np.bincount(inv, minlength=n).astype(np.float64)
    mx = np.bincount(inv, points[:, 0], n) / cnt
    my = np.bincount(inv, points[:, 1], n) / cnt
    nx = np.bincount(inv, normals[:, 0], n)
    ny = np.bincount(inv, normals[:, 1], n)
    length = np.hypot(nx, ny)
    ok = length >= min_normal_agreement * cnt
    return (np.stack([mx[ok], my[ok]], axis=1),
            np.stack([nx[ok] / length[ok], ny[ok] / length[ok]], axis=1))


def local_point_map(keyframes: Sequence[Keyframe], T_map_kf: F64, voxel_m: float) -> PointMap:
    """Scan-to-map target: the keyframes' points with normals in the map frame, averaged per
    ``voxel_m`` cell (no averaging if 0)."""
    pts, nrm = gather(keyframes, T_map_kf)
    if voxel_m > 0:
        pts, nrm = voxel_mean(pts, nrm, voxel_m)
    return PointMap(pts, nrm)


def points_in_frame(keyframes: Sequence[Keyframe], T_map_kf: F64, T_map_frame: F64,
                    voxel_m: float, max_range_m: float | None = None) -> tuple[F64, F64]:
    """Keyframes' points with normals in the frame ``T_map_frame``, thinned to ``voxel_m``;
    with ``max_range_m``, points farther than that from their own keyframe are dropped."""
    rel = between(T_map_frame, T_map_kf).reshape(-1, 3)
    pts, nrm = gather(keyframes, rel)
    if max_range_m is not None and len(pts):
        ranges = np.concatenate([kf.matchable.ranges_m for kf in keyframes])
        keep = ranges <= max_range_m
        pts, nrm = pts[keep], nrm[keep]
    p, n = voxel_thin(pts, voxel_m, nrm)
    return p, n


def nearest_keyframes(T_map_kf: F64, index: int, n: int) -> NDArray[np.int64]:
    """Indices of the ``n`` keyframes (poses ``T_map_kf``, (K, 3)) nearest keyframe ``index``,
    itself included, in keyframe order (ties: the earlier)."""
    d = np.hypot(*(T_map_kf[:, :2] - T_map_kf[index, :2]).T)
    return np.sort(np.argsort(d, kind="stable")[:n])


def reusable_keyframe(T_map_kf: F64, T_map_robot: F64, anchor: int, reuse_m: float,
                      reuse_deg: float) -> int | None:
    """The keyframe other than ``anchor`` nearest the robot, within ``reuse_m`` of it and
    facing within ``reuse_deg`` of its heading: where the robot passes again, the pipeline
    goes on from it instead of adding a keyframe (``keyframes.reuse``). None if none is."""
    d = np.hypot(T_map_kf[:, 0] - T_map_robot[0], T_map_kf[:, 1] - T_map_robot[1])
    turn = np.abs(wrap_angle(T_map_kf[:, 2] - T_map_robot[2]))
    ok = (d <= reuse_m) & (turn <= math.radians(reuse_deg))
    ok[anchor] = False
    if not ok.any():
        return None
    return int(np.flatnonzero(ok)[np.argmin(d[ok])])
