"""Cells the map has shown as walls at some decision, remembered in world-aligned cells.

Beams that skim along a wall at a shallow angle cross the wall's own cells before they end
further along it, and clear them: a wall seen from afar fades into free cells with unknown space
right behind, which looks exactly like an open frontier. Standing next to it restores it (the
beams then hit it square on), driving away fades it again — a robot would shuttle back and forth.
So the explorer remembers every cell it has once seen occupied and keeps frontiers off them.
The memory only shapes frontiers; planning always uses the current map.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from server.planning.grid import GridGeometry, OccupancyGrid


class WallMemory:
    """A growing set of cells (world-aligned at one resolution) once seen occupied."""

    def __init__(self) -> None:
        self.resolution_m: float | None = None
        self._keys = np.zeros(0, np.int64)       # sorted unique ix << 32 | iy (offset)

    _OFFSET = 1 << 30

    def __len__(self) -> int:
        return len(self._keys)

    def clear(self) -> None:
        """Forget everything (e.g. when the map's frame changes)."""
        self._keys = np.zeros(0, np.int64)

    def _world_cells(self, geo: GridGeometry, rc: NDArray[np.int64]) -> NDArray[np.int64]:
        xy = geo.cell_to_world(rc)
        ixy = np.floor(xy / geo.resolution_m).astype(np.int64) + self._OFFSET
        return (ixy[:, 0] << 32) | ixy[:, 1]

    def update(self, grid: OccupancyGrid) -> None:
        """Add the grid's occupied cells (a new resolution starts a new memory)."""
        if self.resolution_m != grid.resolution_m:
            self.resolution_m, self._keys = grid.resolution_m, np.zeros(0, np.int64)
        rc = np.argwhere(grid.occupied)
        if len(rc):
            self._keys = np.union1d(self._keys, self._world_cells(grid.geometry, rc))

    def mask(self, geo: GridGeometry) -> NDArray[np.bool_]:
        """The remembered cells inside a grid of geometry ``geo`` (same resolution)."""
        out = np.zeros(geo.shape, bool)
        if not len(self._keys) or self.resolution_m != geo.resolution_m:
            return out
        ix = (self._keys >> 32) - self._OFFSET
        iy = (self._keys & 0xFFFFFFFF) - self._OFFSET
        # cell (row, col) of the grid holds world cell (iy, ix) when its centre lies in it
        x0 = int(np.floor((geo.origin_xy[0] + 0.5 * geo.resolution_m) / geo.resolution_m))
        y0 = int(np.floor((geo.origin_xy[1] + 0.5 * geo.resolution_m) / geo.resolution_m))
        col, row = ix - x0, iy - y0
        ok = (row >= 0) & (row < geo.shape[0]) & (col >= 0) & (col < geo.shape[1])
        out[row[ok], col[ok]] = True
        return out
