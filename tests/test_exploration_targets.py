"""Target placement on reachable cells, frontier hygiene next to walls, the wall memory."""

from __future__ import annotations

import numpy as np

from server.exploration import (
    AnalysisParams,
    Decision,
    ExplorerParams,
    VisitedTargets,
    VoronoiExplorer,
    analyse,
    frontier_mask,
)
from server.exploration.targets import TargetPlacer, reachable_mask
from server.exploration.walls import WallMemory
from server.planning import CostParams, OccupancyGrid, build_cost_layer

RES = 0.1


def room_with_fan() -> OccupancyGrid:
    """A 4 × 3 m room (x 1–5, y 1–4) with a 1 m doorway in its right wall (y 2–3); through the
    doorway the robot has seen only a thin fan of free cells, 0.2 m wide, reaching 2 m beyond."""
    d = np.full((60, 100), -1, np.int8)
    d[10:40, 10:50] = 0
    d[9, 9:51] = 100
    d[40, 9:51] = 100
    d[9:41, 9] = 100
    d[9:41, 50] = 100
    d[20:30, 50] = 0                 # the doorway
    d[24:26, 51:71] = 0              # the fan seen through it
    return OccupancyGrid(d, RES, (0.0, 0.0))


def test_thin_fan_frontier_is_approached_from_a_reachable_cell() -> None:
    g = room_with_fan()
    a = analyse(g, AnalysisParams())
    # the fan is too thin to stand in: all of its cells are lethal
    geo = a.grid.geometry
    fan = geo.world_to_cell(np.array([[6.0, 2.5]]))[0]
    assert not np.isfinite(a.layer.cost[fan[0], fan[1]])
    out = VoronoiExplorer(ExplorerParams(lam=1.0)).decide(g, (2.0, 2.5, 0.0), (2.0, 2.5, 0.0),
                                                          VisitedTargets())
    assert isinstance(out, Decision)
    tx, ty = out.target_xy
    rc = geo.world_to_cell(np.array([tx, ty]))
    assert np.isfinite(a.layer.cost[rc[0], rc[1]])       # a cell the robot may stand on
    assert 4.0 < tx < 5.2 and 2.0 < ty < 3.0              # at the doorway, facing the fan


def test_placement_needs_reachable_cells_and_a_clear_line() -> None:
    g = room_with_fan()
    layer = build_cost_layer(g, CostParams())
    reach = reachable_mask(layer, [np.array([2.0, 2.5])], escape_radius_m=0.5)
    assert reach[25, 20] and not reach[25, 60]
    placer = TargetPlacer(layer, reach, g.occupied)
    # a point in the room moves nowhere; one in the wall moves into the room; far ones: None
    got = placer.points(np.array([[25, 20], [9, 30], [25, 90]]), radius_m=0.5)
    assert got[0] == (25, 20)
    assert got[1] is not None and 10 <= got[1][0] <= 13
    assert got[2] is None
    # nothing reachable from a start outside the grid
    assert not reachable_mask(layer, [np.array([-5.0, -5.0])], 0.5).any()
    # a cell behind a wall is not approached across it
    assert not placer._clear_line((15, 20), (15, 55))
    assert placer._clear_line((25, 20), (25, 45))


def test_frontier_cells_keep_off_walls() -> None:
    space = np.zeros((20, 20), bool)
    space[5:15, 5:15] = True
    unexplored = np.zeros((20, 20), bool)
    unexplored[5:15, 15] = True          # open along the right side
    walls = np.zeros((20, 20), bool)
    walls[4, :] = walls[15, :] = True    # top and bottom walls
    walls[8, 15] = True                  # a wall stub in the opening
    plain = frontier_mask(space, unexplored)
    kept = frontier_mask(space, unexplored, walls)
    assert plain[5:15, 14].all()
    assert not kept[5, 14] and not kept[14, 14]           # next to the walls
    assert not kept[7:10, 14].any()                      # next to the stub
    assert kept[11:14, 14].all()


def test_wall_memory_round_trip_and_suppresses_faded_walls() -> None:
    g = room_with_fan()
    mem = WallMemory()
    mem.update(g)
    assert len(mem) == int(g.occupied.sum())
    # the same cells come back in a shifted crop of the grid
    crop = g.crop(5, 45, 5, 55)
    assert np.array_equal(mem.mask(crop.geometry), crop.occupied)
    # a grazed wall: its cells cleared, unknown behind it
    d = g.data.copy()
    d[40, 20:40] = 0
    faded = OccupancyGrid(d, RES, g.origin_xy)
    open_ = analyse(faded, AnalysisParams())
    kept = analyse(faded, AnalysisParams(), walls_seen=mem)
    low = lambda a: a.frontiers.mask[a.frontiers.mask.shape[0] // 2 + 5:].sum()  # noqa: E731
    assert low(open_) > 0 and low(kept) == 0
    # another resolution starts afresh
    mem.update(OccupancyGrid(np.zeros((5, 5), np.int8), 0.05, (0.0, 0.0)))
    assert len(mem) == 0


def hall_open_along_one_side() -> OccupancyGrid:
    """An 8 × 2 m hall (x 1–9, y 1–3) whose upper side has not been seen: one frontier 8 m
    long, like the edge of what grazing beams showed of a long room."""
    d = np.full((60, 110), -1, np.int8)
    d[10:30, 10:90] = 0
    d[9, 9:91] = 100
    d[9:31, 9] = 100
    d[9:31, 90] = 100
    return OccupancyGrid(d, RES, (0.0, 0.0))


def test_one_robot_looks_across_a_long_frontier_from_its_near_end() -> None:
    g = hall_open_along_one_side()
    robot = np.array([1.6, 1.6])
    a = analyse(g, AnalysisParams())
    assert len(a.frontiers) == 1
    reach = reachable_mask(a.layer, [robot], escape_radius_m=0.5)
    placer = TargetPlacer(a.layer, reach, a.grid.occupied)
    geo = a.grid.geometry
    middle = placer.frontiers(a.frontiers, 1.0)[0]
    near = placer.frontiers(a.frontiers, 1.0, geo.world_to_cell(robot).astype(float))[0]
    assert middle is not None and near is not None
    x_mid = geo.cell_to_world(np.array([middle]))[0, 0]
    x_near = geo.cell_to_world(np.array([near]))[0, 0]
    assert 4.0 < x_mid < 6.0 and x_near < 3.0
    # the Voronoi explorer, deciding for one robot, goes to the near end: a few steps there
    # show the whole hall, where its middle is a 4 m drive
    out = VoronoiExplorer(ExplorerParams(lam=1.0)).decide(g, (*robot, 0.0), (*robot, 0.0),
                                                          VisitedTargets())
    assert isinstance(out, Decision) and out.target_xy[0] < 3.0
