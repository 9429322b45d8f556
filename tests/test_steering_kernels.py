"""The compiled loops of every scan's steering and mapping give what the numpy code they
replaced gave, to the bit: pure pursuit's closest point, VFH's blocked sectors, the lookout's
free-space check and the grid's nav2 export. The numpy code is kept here as the reference."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from schemas.occupancy import OCCUPIED, UNKNOWN
from schemas.se2 import transform_points, wrap_angle
from server.control.pure_pursuit import closest_point
from server.control.vfh import Vfh
from server.lookout.movers import LookParams, moving_objects
from server.planning import OccupancyGrid as PlanningGrid
from server.slam.grid import SCALE, UNKNOWN_Q, OccupancyGrid, nav2_formula

F64 = NDArray[np.float64]


def _closest_numpy(path_xy: F64, p: F64, first: int, last: int | None
                   ) -> tuple[int, float, float]:
    a = path_xy[first:(None if last is None else last + 1)]
    b = path_xy[first + 1:(None if last is None else last + 2)]
    a = a[:len(b)]
    d = b - a
    L2 = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    q = a + t[:, None] * d
    dist = np.hypot(*(q - p).T)
    k = int(np.argmin(dist))
    return first + k, float(t[k]), float(dist[k])


def _blocked_numpy(vfh: Vfh, pts: F64, others: F64) -> tuple[NDArray[np.bool_], float]:
    p = vfh.params
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    others = others[np.all(np.isfinite(others), axis=1)]
    xy = np.concatenate([pts, others])
    extra = np.concatenate([np.zeros(len(pts)), np.full(len(others), p.other_robot_radius_m)])
    d = np.hypot(xy[:, 0], xy[:, 1])
    surface = d - extra
    nearest = float(np.min(surface)) if len(d) else math.inf
    radius = p.robot_radius_m + p.safety_m + extra
    use = (surface < p.window_m) & (d - radius < p.block_distance_m) & (d > 1e-6)
    if not use.any():
        return np.zeros(p.sectors, dtype=bool), nearest
    d, r = d[use], radius[use]
    beta = np.arctan2(xy[use, 1], xy[use, 0])
    gamma = np.arcsin(np.minimum(1.0, r / d))
    centres = -math.pi + (np.arange(p.sectors) + 0.5) * (2 * math.pi / p.sectors)
    diff = np.abs(wrap_angle(centres[None, :] - beta[:, None]))
    return np.any(diff <= (gamma + math.pi / p.sectors)[:, None], axis=0), nearest


def _movers_numpy(points_robot: F64, pose: F64, grid: PlanningGrid, mates_xy: F64,
                  p: LookParams, max_range_m: float) -> list[tuple[F64, int]]:
    pts = points_robot
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
    h, w = grid.data.shape
    ok = (ix >= 1) & (iy >= 1) & (ix < w - 1) & (iy < h - 1)
    if not ok.any():
        return []
    free = np.zeros(len(world), dtype=bool)
    g = grid.data
    sel = np.flatnonzero(ok)
    block = np.stack([g[iy[sel] + dy, ix[sel] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    free[sel] = np.all((block != UNKNOWN) & (block < p.free_below), axis=0)
    cand = world[free]
    cand = cand[np.argsort(np.hypot(*(cand - pose[:2]).T))]
    groups: list[tuple[F64, int]] = []
    while len(cand):
        near = np.hypot(*(cand - cand[0]).T) <= p.cluster_m
        groups.append((cand[near].mean(axis=0), int(near.sum())))
        cand = cand[~near]
    return groups


def test_closest_point_is_the_vectorised_searchs() -> None:
    rng = np.random.default_rng(3)
    for k in range(500):
        n = int(rng.integers(2, 40))
        path = np.cumsum(rng.normal(0.0, 0.1, (n, 2)), axis=0)
        if k % 5 == 0:
            path[rng.integers(0, n)] = path[rng.integers(0, n)]   # zero-length segments
        p = path[rng.integers(0, n)] + rng.normal(0.0, 0.3, 2)
        first = int(rng.integers(0, n - 1))
        last = None if k % 4 == 0 else int(rng.integers(first, n + 2))
        assert closest_point(path, p, first, last) == _closest_numpy(path, p, first, last)


def test_vfh_blocks_the_sectors_the_matrix_blocked() -> None:
    rng = np.random.default_rng(4)
    vfh = Vfh()
    some = 0
    for k in range(400):
        pts = rng.uniform(-1.2, 1.2, (int(rng.integers(0, 40)), 2))
        if k % 3 == 0:   # bearings on sector borders and at ±π
            ang = vfh._centres[rng.integers(0, 72, len(pts))] + math.pi / 72 * rng.choice(
                [-1.0, 0.0, 1.0], len(pts))
            pts = np.stack([np.cos(ang), np.sin(ang)], axis=1) * rng.uniform(0.2, 0.6,
                                                                             (len(pts), 1))
        others = rng.uniform(-1.0, 1.0, (int(rng.integers(0, 3)), 2))
        if k % 7 == 0 and len(pts):   # returns that are not numbers are left out
            pts[rng.integers(0, len(pts))] = (np.nan, 1.0)
        got, nearest = vfh.blocked_sectors(pts, others)
        want, nearest0 = _blocked_numpy(vfh, pts, others)
        np.testing.assert_array_equal(got, want)
        assert nearest == nearest0
        some += int(want.any() and not want.all())
    assert some > 100


def test_movers_check_the_same_free_cells() -> None:
    rng = np.random.default_rng(5)
    p = LookParams()
    found = 0
    for _ in range(150):
        h, w = (int(v) for v in rng.integers(20, 120, 2))
        data = rng.choice(np.array([UNKNOWN, 0, 10, 24, 25, 60, 100], dtype=np.int8), (h, w),
                          p=[0.05, 0.6, 0.2, 0.05, 0.03, 0.03, 0.04])
        grid = PlanningGrid(data, 0.05, (float(rng.uniform(-2, 0)), float(rng.uniform(-2, 0))))
        pose = np.array([*rng.uniform(0.0, 2.0, 2), rng.uniform(-math.pi, math.pi)])
        pts = rng.uniform(-4.0, 4.0, (int(rng.integers(0, 360)), 2))
        mates = rng.uniform(-1.0, 3.0, (int(rng.integers(0, 3)), 2))
        got = moving_objects(pts, pose, grid, mates, p, 3.5)
        want = _movers_numpy(pts, pose, grid, mates, p, 3.5)
        assert len(got) == len(want)
        for (c, n), (c0, n0) in zip(got, want, strict=True):
            np.testing.assert_array_equal(c, c0)
            assert n == n0
        found += len(want)
    assert found > 100


def test_nav2_export_is_the_formulas_for_every_value() -> None:
    every = np.arange(1 << 16, dtype=np.uint16).view(np.int16).reshape(256, 256)
    want = nav2_formula(every)
    np.testing.assert_array_equal(OccupancyGrid.nav2_of(every), want)
    np.testing.assert_array_equal(OccupancyGrid.nav2_of(every[:, ::3]), want[:, ::3])
    # the formula itself: unknown is -1, log-odds 0 is 50 %, the clamps' ends near 0 and 100
    assert want.reshape(-1)[np.uint16(UNKNOWN_Q)] == UNKNOWN
    assert want.reshape(-1)[0] == OCCUPIED // 2
    assert want.reshape(-1)[np.uint16(np.int16(round(-2.0 * SCALE)))] == 12
