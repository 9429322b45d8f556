"""Frontiers: known free cells next to unexplored space, grouped into clusters.

Walls seen at a grazing angle get holes: beams that pass along them clear some wall cells, or
leave them uncertain. A free cell in such a hole touches the unknown space behind the wall, but
no robot position on this side will ever see through it, so it would stay a frontier for good
and draw the robot back again and again. Frontier cells therefore must not touch (8-connected)
a wall cell — occupied, or observed without a verdict — when the walls are given; real openings
(a doorway, the open end of a corridor) keep their cells away from the jambs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from server.exploration.frontiers_kernel import clusters


@dataclass(frozen=True, eq=False)
class Frontiers:
    """Frontier clusters of at least the minimum size, as cells of the analysed grid."""

    mask: NDArray[np.bool_]            # (H, W) cells of the kept clusters
    cells_rc: NDArray[np.int64]        # (M, 2) the same cells
    cell_cluster: NDArray[np.int64]    # (M,) cluster index of each cell, 0..K-1
    centroid_rc: NDArray[np.float64]   # (K, 2) mean cell of each cluster
    middle_rc: NDArray[np.int64]       # (K, 2) the cluster's cell nearest to its centroid
    size_cells: NDArray[np.int64]      # (K,)

    def __len__(self) -> int:
        return len(self.size_cells)


def frontier_mask(space: NDArray[np.bool_], unexplored: NDArray[np.bool_],
                  walls: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
    """Cells of ``space`` (known free) with a 4-neighbour in ``unexplored`` and, when ``walls``
    is given, no 8-neighbour in ``walls``."""
    mask = space & dilate(unexplored, eight=False)
    if walls is not None:
        mask &= ~dilate(walls, eight=True)
    return mask


def dilate(m: NDArray[np.bool_], *, eight: bool) -> NDArray[np.bool_]:
    """``m`` grown by one cell, to the 8-neighbours or to the 4-neighbours (cells outside the
    array count as unset): ``ndimage.binary_dilation`` with that structure, by shifted ORs."""
    rows = m.copy()
    rows[1:] |= m[:-1]
    rows[:-1] |= m[1:]
    out = rows.copy() if eight else rows
    src = rows if eight else m
    out[:, 1:] |= src[:, :-1]
    out[:, :-1] |= src[:, 1:]
    return out


def find_frontiers(space: NDArray[np.bool_], unexplored: NDArray[np.bool_], *,
                   min_cells: int, walls: NDArray[np.bool_] | None = None) -> Frontiers:
    """Frontier cells (see :func:`frontier_mask`) grouped 8-connected; clusters with fewer than
    ``min_cells`` are dropped."""
    return cluster_frontiers(frontier_mask(space, unexplored, walls), min_cells=min_cells)


def cluster_frontiers(mask: NDArray[np.bool_], *, min_cells: int) -> Frontiers:
    """Frontier cells ``mask`` grouped 8-connected; clusters under ``min_cells`` are dropped."""
    flat, cell_cluster, k = clusters(np.ascontiguousarray(mask, dtype=bool), max(1, min_cells))
    W = mask.shape[1]
    mask = np.zeros(mask.shape, dtype=bool)
    mask.ravel()[flat] = True
    cells = np.stack(np.divmod(flat, W), axis=1).astype(np.int64)
    size = np.bincount(cell_cluster, minlength=k).astype(np.int64)
    if k == 0:
        empty = np.zeros((0, 2))
        return Frontiers(mask, cells.reshape(0, 2), cell_cluster, empty,
                         empty.astype(np.int64), size)
    centroid = np.stack([np.bincount(cell_cluster, weights=cells[:, i], minlength=k)
                         for i in (0, 1)], axis=1) / size[:, None]
    d2 = np.sum((cells - centroid[cell_cluster]) ** 2, axis=1)
    order = np.lexsort((d2, cell_cluster))
    first = order[np.searchsorted(cell_cluster[order], np.arange(k))]
    return Frontiers(mask, cells, cell_cluster, centroid, cells[first], size)
