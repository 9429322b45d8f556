"""A world from an occupancy grid (a nav2 map image): occupied cells become obstacles.

The cells' outline becomes ray-casting segments (cell edges between an occupied and a
non-occupied cell, merged along each grid line, oriented with the obstacle on the left), and
each horizontal run of occupied cells becomes a rectangle for rasterising. Unknown cells are not
obstacles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from schemas.occupancy import OCCUPIED
from sim.errors import WorldError
from sim.grid import OCCUPIED_THRESH, OccupancyGrid, read_nav2
from sim.world import World


def load_map_world(yaml_path: str | Path, lidar_height_m: float = 0.2) -> World:
    path = Path(yaml_path)
    grid = read_nav2(path)
    world = world_from_grid(grid, path.stem, str(path), lidar_height_m)
    if not len(world.segments):
        raise WorldError(f"{path}: the map has no occupied cells")
    return world


def world_from_grid(grid: OccupancyGrid, name: str, source: str,
                    lidar_height_m: float = 0.2) -> World:
    occ = grid.cells.astype(np.int16) > OCCUPIED_THRESH * OCCUPIED
    res = grid.resolution_m
    ox, oy = grid.origin[0], grid.origin[1]
    segments = np.vstack([_horizontal_edges(occ, res, ox, oy),
                          _vertical_edges(occ, res, ox, oy)])
    rects = []
    for row in range(occ.shape[0]):
        for c0, c1 in _runs(occ[row]):
            x0, x1 = ox + c0 * res, ox + c1 * res
            y0, y1 = oy + row * res, oy + (row + 1) * res
            rects.append(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))
    return World.from_shapes(name, source, rects, np.zeros((0, 3)), lidar_height_m,
                             segments=segments)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index pairs of the True runs of a 1-D mask."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def _horizontal_edges(occ: np.ndarray, res: float, ox: float, oy: float) -> np.ndarray:
    """Edges on the lines y = oy + i * res between rows i-1 (below) and i (above)."""
    h, _ = occ.shape
    padded = np.vstack([np.zeros((1, occ.shape[1]), bool), occ, np.zeros((1, occ.shape[1]), bool)])
    out = []
    for i in range(h + 1):
        below, above = padded[i], padded[i + 1]
        y = oy + i * res
        for c0, c1 in _runs(below & ~above):   # obstacle below: run towards -x
            out.append((ox + c1 * res, y, ox + c0 * res, y))
        for c0, c1 in _runs(above & ~below):   # obstacle above: run towards +x
            out.append((ox + c0 * res, y, ox + c1 * res, y))
    return np.array(out, dtype=np.float64).reshape(-1, 4)


def _vertical_edges(occ: np.ndarray, res: float, ox: float, oy: float) -> np.ndarray:
    """Edges on the lines x = ox + j * res between columns j-1 (left) and j (right)."""
    t = _horizontal_edges(occ.T, res, oy, ox)  # same problem with x and y swapped
    # Swapping axes mirrors orientation: (y, x) runs become (x, y) runs, reversed.
    return np.column_stack([t[:, 3], t[:, 2], t[:, 1], t[:, 0]]) if len(t) else t
