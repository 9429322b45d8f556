"""A robot's map of part of a world without driving it there: scans ray-cast from free places
of a box, inserted into an occupancy grid in the robot's own frame. For tests and benchmarks
of what works on maps (map matching), where a whole simulated run would only add time."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose, inverse
from server.slam.grid import GridParams, OccupancyGrid
from sim.raycast import RayCaster

F64 = NDArray[np.float64]


def scanned_map(caster: RayCaster, lo: tuple[float, float], hi: tuple[float, float],
                start: F64, seed: int, step_m: float = 1.5, resolution_m: float = 0.125,
                range_m: float = 12.0, beams: int = 360) -> tuple[OccupancyGrid, F64]:
    """The map a robot starting at ``start`` (world pose) has after scanning from places
    ``step_m`` apart (jittered by ``seed``) in the box [lo, hi] that are at least 0.5 m from
    any wall, in its own frame; and those places in that frame (its keyframes)."""
    rng = np.random.default_rng(seed)
    grid = OccupancyGrid(GridParams(resolution_m=resolution_m, max_ray_m=range_m))
    inc = 2 * math.pi / beams
    a = -math.pi + inc * np.arange(beams)
    kf = []
    for x in np.arange(lo[0], hi[0], step_m):
        for y in np.arange(lo[1], hi[1], step_m):
            pose = (x + rng.uniform(-0.3, 0.3), y + rng.uniform(-0.3, 0.3),
                    rng.uniform(-math.pi, math.pi))
            r = caster.cast(pose, beams, -math.pi, inc, range_m)
            if not np.isfinite(r).any() or np.nanmin(r) < 0.5:
                continue   # inside a wall or too close to one: no robot stands there
            ok = np.isfinite(r)
            hits = np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1)
            own = compose(inverse(np.asarray(start, dtype=np.float64)), np.array(pose))
            grid.ensure_contains(own[:2] - range_m - 0.5, own[:2] + range_m + 0.5)
            grid.insert_scan(own, hits)
            kf.append(own[:2])
    return grid, np.array(kf).reshape(-1, 2)


def box_pairs(lo: F64, hi: F64, box_m: float, n: int, seed: int
              ) -> list[tuple[F64, F64, F64, F64]]:
    """``n`` pairs of boxes in the world's extent [lo, hi], with each robot's start pose:
    (centre a, centre b, start a, start b). Even pairs overlap (b's box shifted by 0.35 to
    0.6 of a box), odd ones lie apart; starts anywhere, turned anyhow."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        ca = rng.uniform(lo + box_m / 2, hi - box_m / 2)
        if k % 2 == 0:
            d = rng.uniform(0.35, 0.6) * box_m
            ang = rng.uniform(0, 2 * math.pi)
            cb = np.clip(ca + d * np.array([math.cos(ang), math.sin(ang)]),
                         lo + box_m / 2, hi - box_m / 2)
        else:
            for _ in range(100):
                cb = rng.uniform(lo + box_m / 2, hi - box_m / 2)
                if np.abs(cb - ca).max() > box_m + 1.0:
                    break
        Sa = np.array([*rng.uniform(lo, hi), rng.uniform(-math.pi, math.pi)])
        Sb = np.array([*rng.uniform(lo, hi), rng.uniform(-math.pi, math.pi)])
        out.append((ca, cb, Sa, Sb))
    return out
