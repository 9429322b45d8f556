"""The Voronoi graph of known free space: EDT ridge cells, thinned, cut into nodes and edges.

A free cell lies on the generalised Voronoi diagram when it and an 8-neighbour have nearest
boundary cells (the EDT feature transform) at least ``min_separation`` apart: the two cells are
then closest to different stretches of boundary (walls, or the edge of the unknown). Requiring a
separation prunes the tiny ridges a jagged boundary produces; ridges into a concave corner stop
``≈ min_separation/√2`` short of it. The marked band is thinned to one cell (Zhang–Suen).

Graph: skeleton cells with ≥ 3 skeleton neighbours form junction clusters (one node each), cells
with one neighbour are end nodes; the remaining cells form branches, each an edge between the
nodes it touches. A node's degree is the number of distinct branches it touches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from server.exploration.skeleton_kernel import REMOVAL, ridge_cells, thin
from server.planning.edt_kernel import edt_with_indices
from server.planning.grid import EIGHT_CONNECTED

JUNCTION, END = 2, 1
_NEIGHBOURS = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], dtype=np.uint8)
_ALL_OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1), (0, -1), (-1, 0), (-1, -1), (-1, 1))


def _pair_slices(dr: int, dc: int, shape: tuple[int, ...]
                 ) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Slices a, b such that cell a[k] and cell b[k] are neighbours at offset (dr, dc)."""
    H, W = shape
    a = (slice(max(0, -dr), H - max(0, dr)), slice(max(0, -dc), W - max(0, dc)))
    b = (slice(max(0, dr), H + min(0, dr)), slice(max(0, dc), W + min(0, dc)))
    return a, b


def voronoi_skeleton(space: NDArray[np.bool_], *, min_separation_cells: float,
                     nearest_boundary: NDArray[np.intp] | None = None) -> NDArray[np.bool_]:
    """One-cell-wide Voronoi skeleton of the ``space`` mask (see the module docstring).

    ``nearest_boundary`` is the (2, H, W) feature transform of ``space`` (row/col of the nearest
    cell outside it, as from ``ndimage.distance_transform_edt(space, return_indices=True)``);
    computed here when not given.
    """
    if not space.any() or space.all():
        return np.zeros_like(space)
    if nearest_boundary is None:
        _, nearest_boundary = edt_with_indices(space)
    ridge = np.zeros(space.shape, dtype=bool)
    ridge_cells(np.ascontiguousarray(space), np.ascontiguousarray(nearest_boundary[0]),
                np.ascontiguousarray(nearest_boundary[1]),
                float(min_separation_cells * min_separation_cells), ridge)
    return thin(ridge, REMOVAL)


@dataclass(frozen=True, eq=False)
class SkeletonGraph:
    """Nodes and edges of a skeleton (cells as (row, col) of the grid the skeleton came from)."""

    skeleton: NDArray[np.bool_]
    node_rc: NDArray[np.int64]          # (N, 2) a representative cell per node
    node_kind: NDArray[np.int8]         # (N,) JUNCTION (cluster of ≥3-neighbour cells) or END
    node_degree: NDArray[np.int64]      # (N,) distinct branches touching the node
    edges: NDArray[np.int64]            # (E, 2) node indices, i < j, self-loops dropped
    edge_length_cells: NDArray[np.int64]  # (E,) cells in the branch

    def neighbours(self, node: int) -> NDArray[np.int64]:
        e = self.edges
        return np.concatenate([e[e[:, 0] == node, 1], e[e[:, 1] == node, 0]])


def skeleton_graph(skeleton: NDArray[np.bool_],
                   clearance: NDArray[np.floating] | None = None) -> SkeletonGraph:
    """Cut a one-cell-wide skeleton into junction / end nodes and branch edges.

    A junction cluster is represented by its cell of largest ``clearance`` (its first cell when
    no clearance is given).
    """
    skel = np.asarray(skeleton, dtype=bool)
    count = ndimage.convolve(skel.astype(np.uint8), _NEIGHBOURS, mode="constant")
    junction = skel & (count >= 3)
    end = skel & (count == 1)
    jlab, nj = ndimage.label(junction, structure=EIGHT_CONNECTED)
    blab, nb = ndimage.label(skel & ~junction, structure=EIGHT_CONNECTED)

    # Junction cluster ↔ branch contacts.
    pairs = []
    for dr, dc in _ALL_OFFSETS:
        a, b = _pair_slices(dr, dc, skel.shape)
        ja, bb = jlab[a], blab[b]
        hit = (ja > 0) & (bb > 0)
        pairs.append(np.stack([ja[hit], bb[hit]], axis=1))
    contact = np.unique(np.concatenate(pairs), axis=0) if pairs else np.zeros((0, 2), int)

    # Nodes: junction clusters 0..nj-1, then end cells.
    j_rc = _cluster_representatives(jlab, nj, clearance)
    end_rc = np.argwhere(end)
    node_rc = np.concatenate([j_rc, end_rc]).astype(np.int64)
    node_kind = np.concatenate([np.full(nj, JUNCTION, np.int8), np.full(len(end_rc), END, np.int8)])

    # Which nodes each branch touches: its junction contacts and its end cells.
    touch_branch = np.concatenate([contact[:, 1], blab[end]]).astype(np.int64)
    touch_node = np.concatenate([contact[:, 0] - 1, nj + np.arange(len(end_rc))]).astype(np.int64)
    branch_len = np.bincount(blab.ravel(), minlength=nb + 1)

    # One edge per pair of nodes a branch touches (almost always exactly two).
    key = np.unique(touch_branch * (len(node_rc) + 1) + touch_node)
    tb, tn = key // (len(node_rc) + 1), key % (len(node_rc) + 1)
    first = np.searchsorted(tb, np.arange(1, nb + 1))
    count = np.bincount(tb, minlength=nb + 1)[1:]
    two = np.flatnonzero(count == 2)
    edges = [np.stack([tn[first[two]], tn[first[two] + 1]], axis=1)]
    lengths = [branch_len[two + 1]]
    for k in np.flatnonzero(count > 2):
        nodes = tn[first[k]:first[k] + count[k]]
        clique = np.array([(a, b) for i, a in enumerate(nodes) for b in nodes[i + 1:]])
        edges.append(clique)
        lengths.append(np.full(len(clique), branch_len[k + 1]))
    edge_arr = np.concatenate(edges).astype(np.int64).reshape(-1, 2)
    degree = np.bincount(edge_arr.ravel(), minlength=len(node_rc)).astype(np.int64)
    # A junction's degree counts branches, including ones that lead nowhere (no second node).
    if nj:
        degree[:nj] = np.bincount(contact[:, 0] - 1, minlength=nj)
    return SkeletonGraph(skel, node_rc, node_kind, degree, edge_arr,
                         np.concatenate(lengths).astype(np.int64))


def _cluster_representatives(labels: NDArray[np.int32], n: int,
                             clearance: NDArray[np.floating] | None) -> NDArray[np.int64]:
    """Per label 1..n, its cell of largest clearance (first in row-major order on ties)."""
    if n == 0:
        return np.zeros((0, 2), dtype=np.int64)
    cells = np.argwhere(labels > 0)
    lab = labels[cells[:, 0], cells[:, 1]]
    weight = (np.zeros(len(cells)) if clearance is None
              else -np.asarray(clearance, dtype=np.float64)[cells[:, 0], cells[:, 1]])
    order = np.lexsort((weight, lab))
    first = order[np.searchsorted(lab[order], np.arange(1, n + 1))]
    return cells[first].astype(np.int64)
