"""Voronoi skeleton, its graph, rule-1 candidates and frontiers on a synthetic T corridor."""

from __future__ import annotations

import numpy as np
import pytest

from server.exploration import (
    AnalysisParams,
    analyse,
    find_frontiers,
    rule1_candidates,
    rule1_junctions,
    skeleton_graph,
    voronoi_skeleton,
)
from server.exploration.skeleton import END, JUNCTION
from server.planning import OccupancyGrid

RES = 0.1


def t_corridor() -> OccupancyGrid:
    """A 1.5 m wide corridor along x from x = 1 to 11 m (y 3.0–4.5 m) whose two ends open onto
    unknown space, with a 1.5 m wide stem going down from its middle (x 5.5–7.0 m) to a walled
    dead end at y = 0.5 m. 10 cm cells, origin (0, 0)."""
    d = np.full((80, 120), -1, np.int8)
    d[30:45, 10:110] = 0
    d[29, 10:110] = 100
    d[45, 10:110] = 100
    d[5:30, 55:70] = 0
    d[5:30, 54] = 100
    d[5:30, 70] = 100
    d[4, 54:71] = 100
    return OccupancyGrid(d, RES, (0.0, 0.0))


def test_skeleton_runs_along_corridor_centres() -> None:
    g = t_corridor()
    a = analyse(g, AnalysisParams())
    geo = a.grid.geometry
    xy = geo.cell_to_world(np.argwhere(a.graph.skeleton))
    mid_corridor = xy[(xy[:, 0] > 2.5) & (xy[:, 0] < 5.0)]
    assert len(mid_corridor) >= 20
    assert np.all(np.abs(mid_corridor[:, 1] - 3.75) <= 0.11)
    stem = xy[(xy[:, 1] > 1.5) & (xy[:, 1] < 2.8)]
    assert len(stem) >= 10
    assert np.all(np.abs(stem[:, 0] - 6.25) <= 0.11)
    # The skeleton stays inside known free space.
    assert not np.any(a.graph.skeleton & ~a.space)


def test_rule1_finds_open_ends_not_dead_end() -> None:
    g = t_corridor()
    a = analyse(g, AnalysisParams())
    gr = a.graph
    junctions, ends = rule1_junctions(gr)
    # Three forks: the two open corridor ends and the walled end of the stem.
    assert len(junctions) == 3
    assert np.all(gr.node_kind[junctions] == JUNCTION)
    assert np.all(gr.node_degree[junctions] == 3)
    assert np.all(gr.node_kind[ends] == END)
    dead_end = a.grid.geometry.cell_to_world(gr.node_rc[junctions])
    assert np.sum(dead_end[:, 1] < 2.0) == 1
    chosen = rule1_candidates(gr, a.frontiers, radius_cells=0.6 / RES)
    xy = a.grid.geometry.cell_to_world(gr.node_rc[chosen])
    assert len(xy) == 2
    xy = xy[np.argsort(xy[:, 0])]
    assert 1.0 < xy[0, 0] < 2.5 and 9.5 < xy[1, 0] < 11.0
    assert np.all(np.abs(xy[:, 1] - 3.75) < 0.5)


def test_graph_of_a_plus_shape() -> None:
    sk = np.zeros((21, 21), bool)
    sk[10, 2:19] = True
    sk[2:19, 10] = True
    gr = skeleton_graph(sk)
    assert np.sum(gr.node_kind == JUNCTION) == 1
    assert np.sum(gr.node_kind == END) == 4
    j = int(np.flatnonzero(gr.node_kind == JUNCTION)[0])
    assert gr.node_degree[j] == 4
    assert sorted(gr.node_kind[gr.neighbours(j)].tolist()) == [END] * 4
    assert len(rule1_junctions(gr)[0]) == 0  # degree 4, not 3


def test_separation_prunes_ridges_of_a_jagged_wall() -> None:
    space = np.zeros((40, 60), bool)
    space[5:35, 5:55] = True
    space[5, 6:54:2] = False  # a comb of one-cell teeth along the bottom wall
    loose = voronoi_skeleton(space, min_separation_cells=1.0)
    tight = voronoi_skeleton(space, min_separation_cells=3.0)
    near_teeth = (slice(5, 10), slice(8, 52))
    assert loose[near_teeth].sum() > tight[near_teeth].sum()
    assert tight[near_teeth].sum() <= 2


def test_frontiers_are_the_two_open_ends() -> None:
    g = t_corridor()
    a = analyse(g, AnalysisParams())
    fr = a.frontiers
    assert len(fr) == 2
    # 15 cells across each open end, less the two touching the corridor walls
    assert sorted(fr.size_cells.tolist()) == [13, 13]
    xy = a.grid.geometry.cell_to_world(fr.middle_rc)
    assert sorted(np.round(xy[:, 0], 2).tolist()) == [1.05, 10.95]
    assert np.allclose(xy[:, 1], 3.75, atol=0.11)


def test_beam_gaps_make_no_frontier_and_min_size_filters() -> None:
    space = np.zeros((30, 30), bool)
    space[5:25, 5:25] = True
    unexplored = ~space
    space[12, 12] = False  # a one-cell gap between beams, not part of unexplored space
    fr = find_frontiers(space, unexplored, min_cells=3)
    assert len(fr) == 1 and not fr.mask[11:14, 11:14].any()
    # A two-cell opening is dropped when clusters need three cells.
    s2 = np.zeros((30, 30), bool)
    s2[5:25, 5:25] = True
    u2 = np.zeros((30, 30), bool)
    u2[4, 10:12] = True
    assert len(find_frontiers(s2, u2, min_cells=3)) == 0
    assert len(find_frontiers(s2, u2, min_cells=2)) == 1


@pytest.mark.parametrize("origin", [(0.0, 0.0), (-37.5, 12.25)])
def test_analysis_is_translation_invariant(origin: tuple[float, float]) -> None:
    g0 = t_corridor()
    g = OccupancyGrid(g0.data, RES, origin)
    a = analyse(g, AnalysisParams())
    chosen = rule1_candidates(a.graph, a.frontiers, radius_cells=6)
    xy = a.grid.geometry.cell_to_world(a.graph.node_rc[chosen]) - np.asarray(origin)
    assert len(xy) == 2 and np.all(np.abs(xy[:, 1] - 3.75) < 0.5)
