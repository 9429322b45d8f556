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
    pts = np.asarray(points_robot, dtype=np.float64).reshape(-1, 2)
    r = np.hypot(pts[:, 0], pts[:, 1])
    pts = pts[(r >= p.min_range_m) & (r <= max_range_m)]
    if len(pts) == 0:
        return []
    world = transform_points(pose, pts)
    if len(mates_xy):
        d = np.hypot(world[:, None, 0] - mates_xy[None, :, 0],
                     world[:, None, 1] - mates_xy[None, :, 1]).min(axis=1)
        world = world[d > p.cluster_m]
    res = grid.resolution_m
    ix = np.floor((world[:, 0] - grid.origin_xy[0]) / res).astype(np.int64)
    iy = np.floor((world[:, 1] - grid.origin_xy[1]) / res).astype(np.int64)
    free = np.zeros(len(world), dtype=bool)
    _free_blocks(np.ascontiguousarray(grid.data), ix, iy, int(p.free_below), free)
    cand = world[free]
    if len(cand) == 0:
        return []
    cand = cand[np.argsort(np.hypot(*(cand - pose[:2]).T))]
    groups: list[tuple[F64, int]] = []
    while len(cand):
        near = np.hypot(*(cand - cand[0]).T) <= p.cluster_m
        groups.append((cand[near].mean(axis=0), int(near.sum())))
        cand = cand[~near]
    return groups


@njit_cached
def _free_blocks(d: NDArray[np.int8], ix: NDArray[np.int64], iy: NDArray[np.int64],
                 free_below: int, free: NDArray[np.bool_]) -> None:
    """``free[i]``: the 3 × 3 cells around (ix[i], iy[i]) lie inside ``d``, none unknown and
    all below ``free_below``."""
    h, w = d.shape
    for i in range(ix.shape[0]):
        x, y = ix[i], iy[i]
        if x < 1 or y < 1 or x >= w - 1 or y >= h - 1:
            continue
        ok = True
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                v = d[y + dy, x + dx]
                if v == UNKNOWN or v >= free_below:
                    ok = False
        free[i] = ok


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
    _free_blocks(np.zeros((3, 3), dtype=np.int8), np.ones(1, dtype=np.int64),
                 np.ones(1, dtype=np.int64), 25, np.zeros(1, dtype=bool))


_warm_up()
