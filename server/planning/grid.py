"""Occupancy grids as the planning, exploration and coverage code sees them.

A grid is a numpy int8 array (H, W) in the nav2 convention: -1 unknown, 0..100 occupancy in
percent; row index = y, column index = x. ``origin_xy`` is the world (x, y) of the lower-left
corner of cell (0, 0) and ``resolution_m`` the side of a cell, so the centre of cell (row, col) is

    x = origin_x + (col + 0.5) · resolution_m,   y = origin_y + (row + 0.5) · resolution_m.

Cells fall into three classes: free (0 ≤ p < 40), occupied (p > 70) and unobserved (unknown, or
observed but uncertain: 40 ≤ p ≤ 70).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from schemas.occupancy import FREE_BELOW, OCCUPIED, OCCUPIED_ABOVE, UNKNOWN
from server.planning.grid_kernel import small_pockets

EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)


class GridError(ValueError):
    """A grid (array, resolution or origin) that cannot be used; the message names the problem."""


@dataclass(frozen=True)
class GridGeometry:
    """World ↔ cell conversions of a grid of ``shape`` = (rows H, cols W)."""

    resolution_m: float
    origin_xy: tuple[float, float]
    shape: tuple[int, int]

    def world_to_cell(self, xy: ArrayLike) -> NDArray[np.int64]:
        """Cells (row, col) holding world points (…, 2) [m]: col = ⌊(x − x0)/res⌋, row alike."""
        p = np.asarray(xy, dtype=np.float64)
        col = np.floor((p[..., 0] - self.origin_xy[0]) / self.resolution_m)
        row = np.floor((p[..., 1] - self.origin_xy[1]) / self.resolution_m)
        return np.stack([row, col], axis=-1).astype(np.int64)

    def cell_to_world(self, rc: ArrayLike) -> NDArray[np.float64]:
        """World (x, y) [m] of the centres of cells (…, 2) given as (row, col)."""
        c = np.asarray(rc, dtype=np.float64)
        x = self.origin_xy[0] + (c[..., 1] + 0.5) * self.resolution_m
        y = self.origin_xy[1] + (c[..., 0] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=-1)

    def contains(self, rc: ArrayLike) -> NDArray[np.bool_]:
        c = np.asarray(rc)
        return ((c[..., 0] >= 0) & (c[..., 0] < self.shape[0])
                & (c[..., 1] >= 0) & (c[..., 1] < self.shape[1]))

    @property
    def cell_area_m2(self) -> float:
        return self.resolution_m * self.resolution_m


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """An occupancy grid with its resolution [m/cell] and origin (see the module docstring)."""

    data: NDArray[np.int8]
    resolution_m: float
    origin_xy: tuple[float, float]

    def __post_init__(self) -> None:
        d = self.data
        if not isinstance(d, np.ndarray) or d.ndim != 2 or d.dtype != np.int8:
            raise GridError("grid data must be a 2-D numpy int8 array, got "
                            f"{type(d).__name__} {getattr(d, 'dtype', '')} "
                            f"{getattr(d, 'shape', '')}")
        if d.size == 0:
            raise GridError("grid data is empty")
        if not (np.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise GridError(f"grid resolution_m must be finite and > 0, got {self.resolution_m}")
        if len(self.origin_xy) != 2 or not np.all(np.isfinite(self.origin_xy)):
            raise GridError(f"grid origin_xy must be two finite numbers, got {self.origin_xy}")
        if int(d.min()) < UNKNOWN or int(d.max()) > OCCUPIED:
            raise GridError(f"grid values must lie in [{UNKNOWN}, {OCCUPIED}], "
                            f"got [{d.min()}, {d.max()}]")
        object.__setattr__(self, "origin_xy", (float(self.origin_xy[0]),
                                               float(self.origin_xy[1])))

    @property
    def geometry(self) -> GridGeometry:
        return GridGeometry(self.resolution_m, self.origin_xy,
                            (int(self.data.shape[0]), int(self.data.shape[1])))

    @cached_property
    def free(self) -> NDArray[np.bool_]:
        return (self.data != UNKNOWN) & (self.data < FREE_BELOW)

    @cached_property
    def occupied(self) -> NDArray[np.bool_]:
        return self.data > OCCUPIED_ABOVE

    @cached_property
    def unobserved(self) -> NDArray[np.bool_]:
        """Unknown cells and cells observed without a verdict (40 ≤ p ≤ 70)."""
        return ~(self.free | self.occupied)

    def crop(self, row0: int, row1: int, col0: int, col1: int) -> OccupancyGrid:
        """The sub-grid rows [row0, row1) × cols [col0, col1), with its origin shifted."""
        H, W = self.data.shape
        row0, col0 = max(0, row0), max(0, col0)
        row1, col1 = min(H, row1), min(W, col1)
        if row1 <= row0 or col1 <= col0:
            raise GridError(f"empty crop rows [{row0}, {row1}) cols [{col0}, {col1})")
        ox = self.origin_xy[0] + col0 * self.resolution_m
        oy = self.origin_xy[1] + row0 * self.resolution_m
        return OccupancyGrid(self.data[row0:row1, col0:col1], self.resolution_m, (ox, oy))

    def crop_to_known(self, margin_cells: int = 2,
                      include_xy: ArrayLike | None = None) -> OccupancyGrid:
        """The bounding box of the observed cells (and of ``include_xy`` points) plus a margin.

        Every computation on the map is done on this box: outside it everything is unknown.
        """
        rows = np.flatnonzero(np.any(self.data != UNKNOWN, axis=1))
        cols = np.flatnonzero(np.any(self.data != UNKNOWN, axis=0))
        if rows.size == 0:
            r0, r1, c0, c1 = self.data.shape[0], -1, self.data.shape[1], -1
        else:
            r0, r1, c0, c1 = int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])
        if include_xy is not None:
            rc = self.geometry.world_to_cell(np.asarray(include_xy, np.float64).reshape(-1, 2))
            r0, r1 = min(r0, int(rc[:, 0].min())), max(r1, int(rc[:, 0].max()))
            c0, c1 = min(c0, int(rc[:, 1].min())), max(c1, int(rc[:, 1].max()))
        if r1 < r0:
            return self
        return self.crop(r0 - margin_cells, r1 + 1 + margin_cells,
                         c0 - margin_cells, c1 + 1 + margin_cells)


def small_components(mask: NDArray[np.bool_], max_cells: int) -> NDArray[np.bool_]:
    """Cells of the 8-connected components of ``mask`` with at most ``max_cells`` cells that do
    not touch the array border.

    Used to find pockets of unobserved cells inside observed space (gaps between LIDAR beams),
    which are treated as free so they neither look like frontiers nor break the skeleton.
    """
    out = np.zeros(mask.shape, dtype=bool)
    if max_cells > 0:
        small_pockets(np.ascontiguousarray(mask, dtype=bool), max_cells, out)
    return out
