"""Looking at what moves: a rendezvous needs the camera on the other robot.

The camera looks forward with a narrow field of view, so two robots can pass a few metres from
each other without either reading the other's tag. The LIDAR sees all around: returns that
fall, as a compact group, into space the map knows to be free (with free cells all around)
are something that moved there — most likely another robot. While the robot still has robots
outside its team, it then turns toward that group, holds still a moment so the camera gets a
few frames, and goes back to its path. A cooldown keeps it from doing this too often.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from server.control import Twist
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
    max_turn_s: float = 4.0
    cooldown_s: float = 15.0
    free_below: int = 25             # nav2 value under which a cell is free


def moving_object(points_robot: F64, pose: F64, grid: OccupancyGrid, mates_xy: F64,
                  p: LookParams) -> float | None:
    """Bearing (robot frame) of a compact group of returns inside known free space, or None.
    Returns near teammates (known positions) do not count."""
    pts = np.asarray(points_robot, dtype=np.float64).reshape(-1, 2)
    if len(pts) < p.min_points:
        return None
    r = np.hypot(pts[:, 0], pts[:, 1])
    pts = pts[(r >= p.min_range_m) & (r <= p.max_range_m)]
    if len(pts) < p.min_points:
        return None
    c, s = math.cos(pose[2]), math.sin(pose[2])
    world = pts @ np.array([[c, s], [-s, c]]) + pose[:2]
    if len(mates_xy):
        d = np.hypot(world[:, None, 0] - mates_xy[None, :, 0],
                     world[:, None, 1] - mates_xy[None, :, 1]).min(axis=1)
        keep = d > p.cluster_m
        world, pts = world[keep], pts[keep]
    res = grid.resolution_m
    ix = np.floor((world[:, 0] - grid.origin_xy[0]) / res).astype(np.int64)
    iy = np.floor((world[:, 1] - grid.origin_xy[1]) / res).astype(np.int64)
    h, w = grid.data.shape
    ok = (ix >= 1) & (iy >= 1) & (ix < w - 1) & (iy < h - 1)
    if not ok.any():
        return None
    free = np.zeros(len(world), dtype=bool)
    d = grid.data
    sel = np.flatnonzero(ok)
    block = np.stack([d[iy[sel] + dy, ix[sel] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    free[sel] = np.all((block >= 0) & (block < p.free_below), axis=0)
    cand = pts[free]
    if len(cand) < p.min_points:
        return None
    centre = np.median(cand, axis=0)
    near = cand[np.hypot(*(cand - centre).T) <= p.cluster_m]
    if len(near) < p.min_points:
        return None
    m = near.mean(axis=0)
    return math.atan2(m[1], m[0])


class Lookout:
    """One robot's turns toward moving things (see the module docstring)."""

    def __init__(self, params: LookParams | None = None) -> None:
        self.p = params or LookParams()
        self.heading: float | None = None    # where to look, map frame
        self.started_s = 0.0
        self.hold_until_s: float | None = None
        self.next_s = -math.inf
        self.looks = 0

    @property
    def active(self) -> bool:
        return self.heading is not None

    def reset(self) -> None:
        self.heading, self.hold_until_s = None, None

    def step(self, now_s: float, pose: F64, points_robot: F64, grid: OccupancyGrid | None,
             mates_xy: F64) -> Twist | None:
        """A command while looking, else None (the navigator drives)."""
        p = self.p
        if self.heading is None:
            if now_s < self.next_s or grid is None:
                return None
            bearing = moving_object(points_robot, pose, grid, mates_xy, p)
            if bearing is None or abs(bearing) <= p.half_fov_rad:
                return None
            self.heading = math.remainder(pose[2] + bearing, 2 * math.pi)
            self.started_s, self.hold_until_s = now_s, None
            self.looks += 1
        err = math.remainder(self.heading - pose[2], 2 * math.pi)
        if self.hold_until_s is None:
            if abs(err) > p.aligned_rad and now_s - self.started_s < p.max_turn_s:
                return Twist(0.0, math.copysign(p.omega_rps, err))
            self.hold_until_s = now_s + p.hold_s
        if now_s < self.hold_until_s:
            return Twist(0.0, 0.0)
        self.reset()
        self.next_s = now_s + p.cooldown_s
        return None
