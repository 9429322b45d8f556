"""The earliest a team could see each change of a world, knowing where the changes are.

A bound for ``bench/known_map.py --changed``, from the world's truth: for each change, the
time the first robot could come in view of it if each robot drove the shortest way at full
speed to the nearest place that sees it, from the moment it was placed. A place sees a change
when it lies within the LIDAR's range on a straight line from the change's outline with no
wall between. Every robot is free to go to every change at once, so the bound is optimistic:
no pass over a map that does not know where the changes are can show a change earlier, nor
all of them earlier than the latest of these.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt
from skimage.graph import MCP_Geometric

from sim.grid import FREE
from sim.world_map import world_map

F64 = NDArray[np.float64]

#: the grid the bound is taken on [m]
RESOLUTION_M = 0.1
#: rays cast from a change's outline
RAYS = 1440


def earliest_sight_s(world: Path, starts: dict[str, tuple[float, float, float]],
                     changes: Sequence[tuple[float, float, float]], v_mps: float,
                     range_m: float, clearance_m: float) -> list[float]:
    """For each change (x, y, radius of its outline) [m]: the earliest simulated time [s] a
    robot could see it. ``starts``: each robot's place and the time it was placed (x, y, t);
    a robot's centre keeps ``clearance_m`` from every wall."""
    grid, _ = world_map(world, RESOLUTION_M)
    res = grid.resolution_m
    free = grid.cells == FREE
    drivable = distance_transform_edt(free) * res >= clearance_m
    rows, cols = free.shape

    def cell(x: float, y: float) -> tuple[int, int]:
        return int((y - grid.origin[1]) / res), int((x - grid.origin[0]) / res)

    arrive = np.full(free.shape, np.inf)
    cost = np.where(drivable, 1.0, np.inf)
    for x, y, t in starts.values():
        r, c = cell(x, y)
        if not (0 <= r < rows and 0 <= c < cols):
            continue
        if not drivable[r, c]:          # a spawn nearer a wall than the clearance
            cost[r, c] = 1.0
        dist, _ = MCP_Geometric(cost, fully_connected=True).find_costs([(r, c)])
        arrive = np.minimum(arrive, t + dist * res / v_mps)
    out = []
    for x, y, radius in changes:
        seen = np.zeros(free.shape, dtype=bool)
        for a in np.linspace(-math.pi, math.pi, RAYS, endpoint=False):
            ux, uy = math.cos(a), math.sin(a)
            for s in np.arange(radius + res, range_m, res / 2):
                r, c = cell(x + s * ux, y + s * uy)
                if not (0 <= r < rows and 0 <= c < cols) or not free[r, c]:
                    break
                seen[r, c] = True
        t = arrive[seen & drivable]
        out.append(float(t.min()) if len(t) else math.inf)
    return out
