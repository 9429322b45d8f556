"""Where a robot should stand to explore a frontier or reach a junction: reachable cells only.

A frontier cell borders unexplored space, and with unexplored space treated as an obstacle every
frontier cell lies inside the robot-radius zone of that space — a frontier itself is never a
place the robot may stand. Likewise a narrow fan of free space seen through a doorway may be
too thin to enter anywhere near its middle. So targets are *placed*:

- a junction (or any point target) moves to the nearest cell the robot can reach within the snap
  radius;
- a frontier cluster gets the reachable cell nearest to one of its cells, trying its cells from
  the one nearest its centroid outwards: the first cell with a reachable cell within the approach
  radius, and no wall on the straight line between the two, wins. From there the robot looks
  across the frontier.

"Reachable" is the 8-connected set of non-lethal cells that contains the robot (after the same
escape from a lethal start the planner makes), so a placed target always has a path.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from server.exploration.frontiers import Frontiers
from server.planning.costmap import CostLayer
from server.planning.edt_kernel import edt_with_indices
from server.planning.grid import EIGHT_CONNECTED

# Frontier cells tried per cluster before it is given up as out of reach.
_TRIES_PER_CLUSTER = 12


def reachable_mask(layer: CostLayer, starts_xy: Iterable[NDArray[np.float64]],
                   escape_radius_m: float) -> NDArray[np.bool_]:
    """Non-lethal cells 8-connected to any of the start positions (empty when every start is
    off the grid or lethal with nothing traversable within ``escape_radius_m``)."""
    free = np.isfinite(layer.cost)
    labels, _ = ndimage.label(free, structure=EIGHT_CONNECTED)
    keep: list[int] = []
    geo = layer.geometry
    for xy in starts_xy:
        rc = geo.world_to_cell(np.asarray(xy, np.float64).reshape(2))
        if not geo.contains(rc):
            continue
        cell = layer.escape((int(rc[0]), int(rc[1])), escape_radius_m)
        if cell is not None:
            keep.append(int(labels[cell]))
    if not keep:
        return np.zeros_like(free)
    return np.isin(labels, np.asarray(keep)) & free


class TargetPlacer:
    """Nearest reachable cells for point and frontier targets (see the module docstring)."""

    def __init__(self, layer: CostLayer, reachable: NDArray[np.bool_],
                 occupied: NDArray[np.bool_]) -> None:
        self.layer = layer
        self.occupied = occupied
        self.any = bool(reachable.any())
        if self.any:
            dist, idx = edt_with_indices(~reachable)   # scipy's, compiled
            self._dist_cells = dist
            self._near_r, self._near_c = idx[0], idx[1]

    def _nearest(self, r: int, c: int, radius_cells: float) -> tuple[int, int] | None:
        if not self.any or self._dist_cells[r, c] > radius_cells:
            return None
        return int(self._near_r[r, c]), int(self._near_c[r, c])

    def _clear_line(self, a: tuple[int, int], b: tuple[int, int]) -> bool:
        """No occupied cell on the straight line between two cell centres."""
        n = int(np.ceil(2 * np.hypot(a[0] - b[0], a[1] - b[1]))) + 1
        t = np.linspace(0.0, 1.0, n)
        rows = np.rint(a[0] + t * (b[0] - a[0])).astype(np.int64)
        cols = np.rint(a[1] + t * (b[1] - a[1])).astype(np.int64)
        return not bool(self.occupied[rows, cols].any())

    def points(self, rc: NDArray[np.int64], radius_m: float) -> list[tuple[int, int] | None]:
        """For each cell (K, 2): the nearest reachable cell within ``radius_m`` (None: none)."""
        k = radius_m / self.layer.geometry.resolution_m
        return [self._nearest(int(r), int(c), k) for r, c in rc]

    def frontiers(self, fr: Frontiers, radius_m: float, toward_rc: NDArray[np.float64] | None = None
                  ) -> list[tuple[int, int] | None]:
        """Per frontier cluster: where to stand to look across it (None: out of reach): near
        its middle, or with ``toward_rc`` (a cell, e.g. the robot's) near its end closest to
        that cell."""
        out: list[tuple[int, int] | None] = [None] * len(fr)
        if not self.any or len(fr) == 0:
            return out
        k = radius_m / self.layer.geometry.resolution_m
        cells = fr.cells_rc
        near_ok = self._dist_cells[cells[:, 0], cells[:, 1]] <= k
        ref = (fr.centroid_rc[fr.cell_cluster] if toward_rc is None
               else np.asarray(toward_rc, np.float64).reshape(1, 2))
        d2 = np.sum((cells - ref) ** 2, axis=1)
        order = np.lexsort((d2, fr.cell_cluster))
        order = order[near_ok[order]]
        clusters = fr.cell_cluster[order]
        starts = np.searchsorted(clusters, np.arange(len(fr)))
        ends = np.searchsorted(clusters, np.arange(len(fr)), side="right")
        for j in range(len(fr)):
            for i in order[starts[j]:min(ends[j], starts[j] + _TRIES_PER_CLUSTER)]:
                f = (int(cells[i, 0]), int(cells[i, 1]))
                stand = self._nearest(f[0], f[1], k)
                if stand is not None and self._clear_line(f, stand):
                    out[j] = stand
                    break
        return out
