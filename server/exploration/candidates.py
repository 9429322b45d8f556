"""The dissertation's rule 1: Voronoi junctions that open onto unexplored space.

A junction node of degree 3 with two end-node neighbours is where a passage of known free
space widens into the fork the skeleton makes in front of an open end (the two end nodes run
into the corners of the known region). Such a junction is a candidate target when it, or one of
its two end nodes, lies within ``radius_cells`` of a frontier cell; forks in front of known dead
ends (walls all round) are thereby left out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from server.exploration.frontiers import Frontiers
from server.exploration.skeleton import END, JUNCTION, SkeletonGraph


def rule1_junctions(graph: SkeletonGraph) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Junctions of degree 3 with exactly two end-node neighbours.

    Returns (junction node indices (K,), their two end nodes (K, 2)).
    """
    e = graph.edges
    if len(e) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.int64)
    kind = graph.node_kind
    # Orient every junction–end edge as (junction, end).
    je = np.concatenate([e[(kind[e[:, 0]] == JUNCTION) & (kind[e[:, 1]] == END)],
                         e[(kind[e[:, 1]] == JUNCTION) & (kind[e[:, 0]] == END)][:, ::-1]])
    n = len(kind)
    ends_per_junction = np.bincount(je[:, 0], minlength=n)
    chosen = np.flatnonzero((kind == JUNCTION) & (graph.node_degree == 3)
                            & (ends_per_junction == 2))
    if len(chosen) == 0:
        return chosen.astype(np.int64), np.zeros((0, 2), np.int64)
    je = je[np.isin(je[:, 0], chosen)]
    je = je[np.lexsort((je[:, 1], je[:, 0]))]
    return chosen.astype(np.int64), je[:, 1].reshape(-1, 2).astype(np.int64)


def rule1_candidates(graph: SkeletonGraph, frontiers: Frontiers,
                     radius_cells: float) -> NDArray[np.int64]:
    """Rule-1 junctions near a frontier (see the module docstring); node indices (K,)."""
    junctions, end_pairs = rule1_junctions(graph)
    if len(junctions) == 0 or len(frontiers.cells_rc) == 0:
        return np.zeros(0, np.int64)
    tree = cKDTree(frontiers.cells_rc)
    probe = np.concatenate([junctions[:, None], end_pairs], axis=1)  # (K, 3) node indices
    dist, _ = tree.query(graph.node_rc[probe.ravel()].astype(np.float64),
                         distance_upper_bound=radius_cells + 1e-9)
    near = np.isfinite(dist).reshape(-1, 3).any(axis=1)
    return junctions[near]
