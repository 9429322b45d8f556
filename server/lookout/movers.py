"""Finding what moved in a scan: compact groups of LIDAR returns in space the map knows to be
free. Most likely another robot (see ``server.lookout``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.occupancy import OCCUPIED_ABOVE, UNKNOWN
from schemas.se2 import transform_points, wrap_angle
from server.jit import njit_cached
from server.planning import OccupancyGrid

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LookParams:
    min_range_m: float = 0.35
    max_range_m: float = 3.5         # where a tag can still be read well
    min_points: int = 3
    cluster_m: float = 0.5           # a robot is small
    half_fov_rad: float = math.radians(20.0)   # already in view: nothing to do
    aligned_rad: float = math.radians(6.0)
    omega_rps: float = 1.0
    hold_s: float = 1.0
    meet_hold_s: float = 3.0         # face a robot known to be close this long: both cameras
                                     # read tags, and two robots' views fix the rotation
    meet_cooldown_s: float = 10.0    # after meeting, close calls wait this long (others wait
                                     # cooldown_s; close calls ignore that one)
    max_turn_s: float = 4.0
    cooldown_s: float = 15.0
    free_below: int = 25             # stricter than FREE_BELOW: clearly free space only
    approach_range_m: float = 10.0   # farther than a tag is read, up to here: go closer (0: no)
    approach_min_points: int = 1     # a robot far away is only a beam or two wide ...
    approach_confirm: int = 5        # ... so it must be seen in this many scans in a row
    track_m: float = 0.8             # one scan to the next, a robot moves less than this
    approach_v_mps: float = 0.3
    approach_stop_m: float = 1.2     # close enough to read its tag's heading, not just its place
    approach_max_s: float = 30.0
    lost_s: float = 2.0


def moving_objects(points_robot: F64, pose: F64, grid: OccupancyGrid, mates_xy: F64,
                   p: LookParams, max_range_m: float) -> list[tuple[F64, int]]:
    """Compact groups of returns inside known free space within ``max_range_m``, nearest
    first: (centre in the map frame, number of returns). Returns near teammates (known
    positions) do not count."""
    pts = np.ascontiguousarray(points_robot, dtype=np.float64).reshape(-1, 2)
    T = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(T[2]), np.sin(T[2])      # as ``transform_points`` has them
    mates = np.ascontiguousarray(mates_xy, dtype=np.float64).reshape(-1, 2)
    cand = np.empty_like(pts)
    n = _free_returns(pts, float(c), float(s), float(T[0]), float(T[1]), p.min_range_m,
                      float(max_range_m), mates, p.cluster_m, np.ascontiguousarray(grid.data),
                      float(grid.origin_xy[0]), float(grid.origin_xy[1]), grid.resolution_m,
                      int(p.free_below), cand)
    if n == 0:
        return []
    cand = cand[:n]
    cand = cand[np.argsort(np.hypot(*(cand - pose[:2]).T))]
    groups: list[tuple[F64, int]] = []
    while len(cand):
        near = np.hypot(*(cand - cand[0]).T) <= p.cluster_m
        groups.append((cand[near].mean(axis=0), int(near.sum())))
        cand = cand[~near]
    return groups


@njit_cached
def _free_returns(pts: F64, c: float, s: float, tx: float, ty: float, min_r: float,
                  max_r: float, mates: F64, cluster_m: float, d: NDArray[np.int8], ox: float,
                  oy: float, res: float, free_below: int, out: F64) -> int:
    """The returns within [min_r, max_r] of the robot, farther than ``cluster_m`` from every
    mate, whose 3 × 3 cells lie inside ``d``, none unknown and all below ``free_below``:
    into ``out`` in the map frame (in order); their count. The arithmetic of the array code
    it replaced (``transform_points``, floor of the offset over the resolution)."""
    h, w = d.shape
    n = 0
    for i in range(pts.shape[0]):
        px, py = pts[i, 0], pts[i, 1]
        r = np.hypot(px, py)
        if not (r >= min_r and r <= max_r):
            continue
        wx = c * px - s * py + tx
        wy = s * px + c * py + ty
        if mates.shape[0]:
            near = np.inf
            for m in range(mates.shape[0]):
                near = min(near, np.hypot(wx - mates[m, 0], wy - mates[m, 1]))
            if not near > cluster_m:
                continue
        x = int(np.floor((wx - ox) / res))
        y = int(np.floor((wy - oy) / res))
        if x < 1 or y < 1 or x >= w - 1 or y >= h - 1:
            continue
        ok = True
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                v = d[y + dy, x + dx]
                if v == UNKNOWN or v >= free_below:
                    ok = False
        if ok:
            out[n, 0], out[n, 1] = wx, wy
            n += 1
    return n


def moving_object(points_robot: F64, pose: F64, grid: OccupancyGrid, mates_xy: F64,
                  p: LookParams) -> float | None:
    """Bearing (robot frame) of the nearest compact group of returns inside known free space
    within tag-reading range, or None."""
    for centre, n in moving_objects(points_robot, pose, grid, mates_xy, p, p.max_range_m):
        if n >= p.min_points:
            return bearing_to(pose, centre)
    return None


def objects_at_range(points_robot: F64, pose: F64, grid: OccupancyGrid | None, range_m: float,
                     tolerance_m: float, width_m: float = 0.45, past_m: float = 0.3
                     ) -> list[F64]:
    """Things standing free about ``range_m`` away (map frame): runs of neighbouring returns
    within ``tolerance_m`` of that distance, no wider than ``width_m``, not on a wall the map
    knows, that the LIDAR sees past on both sides (the beams beside them reach ``past_m``
    farther, or return nothing). Unlike ``moving_objects``, the place need not be known free:
    a robot read through a door often stands where this robot has not mapped yet."""
    pts = np.asarray(points_robot, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3 or not math.isfinite(range_m) or not math.isfinite(tolerance_m):
        return []
    ang = np.arctan2(pts[:, 1], pts[:, 0])
    order = np.argsort(ang)
    pts, ang = pts[order], ang[order]
    r = np.hypot(pts[:, 0], pts[:, 1])
    gaps = np.diff(ang, append=ang[0] + 2 * math.pi)   # from each return to the next
    step = float(np.median(gaps))
    band = np.abs(r - range_m) <= tolerance_m
    if grid is not None and band.any():
        world = transform_points(pose, pts)
        res = grid.resolution_m
        ix = np.floor((world[:, 0] - grid.origin_xy[0]) / res).astype(np.int64)
        iy = np.floor((world[:, 1] - grid.origin_xy[1]) / res).astype(np.int64)
        h, w = grid.data.shape
        inside = (ix >= 0) & (iy >= 0) & (ix < w) & (iy < h)
        wall = np.zeros(len(pts), dtype=bool)
        wall[inside] = grid.data[iy[inside], ix[inside]] > OCCUPIED_ABOVE
        band &= ~wall
    n = len(pts)
    out: list[F64] = []
    done: set[int] = set()
    for i in np.flatnonzero(band):
        if i in done:
            continue
        run = [int(i)]   # band returns from i on, each next to the one before
        while len(run) < n and band[(run[-1] + 1) % n] and gaps[run[-1]] <= 1.5 * step:
            run.append((run[-1] + 1) % n)
        done.update(run)
        if math.hypot(*(pts[run[0]] - pts[run[-1]])) > width_m:
            continue
        before, after = (run[0] - 1) % n, (run[-1] + 1) % n
        mean_r = float(r[run].mean())
        past_before = gaps[before] > 1.5 * step or r[before] >= mean_r + past_m
        past_after = gaps[run[-1]] > 1.5 * step or r[after] >= mean_r + past_m
        if past_before and past_after:
            out.append(transform_points(pose, pts[run].mean(axis=0, keepdims=True))[0])
    return out


def bearing_to(pose: F64, xy: F64) -> float:
    """Bearing [rad] of ``xy`` (map frame) from a robot at ``pose``."""
    return wrap_angle(math.atan2(xy[1] - pose[1], xy[0] - pose[0]) - pose[2])


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    moving_objects(np.array([[0.5, 0.0]]), np.zeros(3),
                   OccupancyGrid(np.zeros((30, 30), dtype=np.int8), 0.05, (-0.75, -0.75)),
                   np.array([[5.0, 5.0]]), LookParams(), 3.5)


_warm_up()
