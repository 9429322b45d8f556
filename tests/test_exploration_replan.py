"""Replanning to a kept target looks around the robot and the target first, and agrees with
a replan on the whole map; with no path in that window it looks at the whole map."""

from __future__ import annotations

import numpy as np

from schemas.occupancy import FREE, OCCUPIED, UNKNOWN
from server.exploration import ExplorerParams
from server.exploration.replan import Replan, _replan_on, replan, replan_window
from server.exploration.walls import WallMemory
from server.planning import OccupancyGrid

RES = 0.1


def corridor_map() -> OccupancyGrid:
    """A 100 × 100 m map: a long explored corridor along y = 0 with a wall across it at
    x = 2 m, except through a detour far up (y = 0 … 20 m) — and unknown beyond x = 25 m."""
    g = np.full((600, 600), UNKNOWN, np.int8)
    g[290:310, 50:500] = FREE                       # corridor y ∈ [-1, 1) m, x ∈ [-25, 20)
    g[289, 50:500] = g[310, 50:500] = OCCUPIED
    g[290:310, 270] = OCCUPIED                      # a wall across it at x = -3 m ...
    g[290:500, 230:250] = FREE                      # ... passed by a detour up to y = 20 m
    g[500:520, 230:300] = FREE
    g[310:520, 280:300] = FREE
    g[290:310, 271:280] = FREE
    g = np.pad(g, 200, constant_values=UNKNOWN)     # (the rest of a large building)
    return OccupancyGrid(g, RES, (-50.0, -50.0))


def job(grid: OccupancyGrid, pose: tuple[float, float], target: tuple[float, float]) -> Replan:
    return Replan(grid, ExplorerParams().analysis, WallMemory(), pose, target, 1.5)


def test_a_replan_near_the_target_looks_at_a_window_and_agrees_with_the_whole_map() -> None:
    grid = corridor_map()
    j = job(grid, (10.0, 0.0), (19.5, 0.0))       # the open end of the corridor
    window = replan_window(j)
    assert window is not None and window.data.size < 0.2 * grid.data.size
    fast, full = replan(j), _replan_on(grid, j)
    assert fast.path_xy is not None and full.path_xy is not None
    length = [float(np.hypot(*np.diff(a.path_xy, axis=0).T).sum()) for a in (fast, full)]
    assert abs(length[0] - length[1]) < 0.2


def test_no_path_in_the_window_falls_back_to_the_whole_map() -> None:
    grid = corridor_map()
    # from behind the wall: the only way goes up the detour, out of the window
    j = job(grid, (-4.5, 0.0), (19.5, 0.0))
    window = replan_window(j)
    assert window is not None
    assert _replan_on(window, j).planning_failed
    answer = replan(j)
    assert answer.path_xy is not None and answer.path_xy[:, 1].max() > 15.0


def test_a_target_that_no_longer_borders_unexplored_space_is_dropped_in_the_window() -> None:
    grid = corridor_map()
    j = job(grid, (10.0, 0.0), (5.0, 0.0))        # mid-corridor: nothing unknown near it
    answer = replan(j)
    assert answer.path_xy is None and not answer.planning_failed
    assert answer.reason == _replan_on(grid, j).reason
