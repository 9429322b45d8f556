"""A* over a cost layer (8-connected) and the single-query planner built on it."""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.planning.astar_kernel import GOING, NO_PATH, Search
from server.planning.costmap import CostLayer
from server.planning.errors import (
    GoalOccupied,
    NoPath,
    OutsideGrid,
    PlanningTimedOut,
    StartOccupied,
    describe_xy,
)
from server.planning.path import Path, shortcut_cells

_TIME_CHECK_EVERY = 2048


def astar_cells(cost: NDArray[np.float64], start: tuple[int, int], goal: tuple[int, int], *,
                min_cost: float, timeout_s: float = 1.0) -> tuple[NDArray[np.int64], float]:
    """Minimum-cost 8-connected cell path from ``start`` to ``goal`` (both non-lethal).

    Edge cost between neighbours a, b: step · (c_a + c_b)/2, step ∈ {1, √2} [cells]. Heuristic:
    octile distance × ``min_cost`` (a lower bound of every cell cost), which is consistent, so
    the first expansion of the goal is optimal. Returns the cells (N, 2) and the cost [cells].
    Raises NoPath when the goal is not reachable, PlanningTimedOut past ``timeout_s``. The
    loop itself is compiled (``server.planning.astar_kernel``); the clock is read every
    2048 expansions from the first.
    """
    H, W = cost.shape
    W2 = W + 2  # padded with a lethal border: neighbours never leave the array
    padded = np.full((H + 2, W2), np.inf)
    padded[1:-1, 1:-1] = cost
    s = (start[0] + 1) * W2 + start[1] + 1
    g_idx = (goal[0] + 1) * W2 + goal[1] + 1
    search = Search(padded, s, g_idx, float(min_cost), _TIME_CHECK_EVERY)
    deadline = time.perf_counter() + timeout_s
    while (status := search.run()) == GOING:
        if time.perf_counter() > deadline:
            raise PlanningTimedOut(f"A* passed {timeout_s:.3f} s after {search.expanded} "
                                   "expansions")
    if status == NO_PATH:
        raise NoPath(f"goal cell {goal} not reachable from {start} ({search.expanded} cells "
                     "expanded)")
    cells = []
    u = g_idx
    parent = search.parent
    while u != -1:
        r, col = divmod(int(u), W2)
        cells.append((r - 1, col - 1))
        u = parent[u]
    cells.reverse()
    return np.asarray(cells, dtype=np.int64), float(search.g[g_idx])


def resolve_endpoints(layer: CostLayer, start_xy: ArrayLike, goal_xy: ArrayLike,
                      escape_radius_m: float) -> tuple[tuple[int, int], tuple[int, int], bool]:
    """Start and goal cells; a lethal start escapes to the nearest traversable cell.

    Returns (start cell, goal cell, whether the start escaped). Raises OutsideGrid,
    StartOccupied (nothing traversable within the escape radius) or GoalOccupied.
    """
    geo = layer.geometry
    start_rc, goal_rc = geo.world_to_cell(start_xy), geo.world_to_cell(goal_xy)
    if not geo.contains(start_rc):
        raise OutsideGrid(f"start {describe_xy(start_xy)} lies outside the grid")
    if not geo.contains(goal_rc):
        raise OutsideGrid(f"goal {describe_xy(goal_xy)} lies outside the grid")
    s = (int(start_rc[0]), int(start_rc[1]))
    g = (int(goal_rc[0]), int(goal_rc[1]))
    if not np.isfinite(layer.cost[g]):
        raise GoalOccupied(f"goal {describe_xy(goal_xy)} is in a lethal cell "
                           f"(clearance {layer.clearance_m[g]:.2f} m)")
    escaped = layer.escape(s, escape_radius_m)
    if escaped is None:
        raise StartOccupied(f"start {describe_xy(start_xy)} is lethal and no traversable "
                            f"cell lies within {escape_radius_m} m")
    return escaped, g, escaped != s


def cells_to_path(layer: CostLayer, cells: NDArray[np.int64], cost_cells: float,
                  start_xy: ArrayLike, goal_xy: ArrayLike, *, escaped: bool,
                  smooth: bool) -> Path:
    """World path: exact start, (shortcut) cell centres, exact goal. With an escaped start the
    first cell centre is kept so the robot first leaves the lethal zone the short way."""
    if smooth:
        cells = shortcut_cells(layer, cells)
    centres = layer.geometry.cell_to_world(cells)
    inner = centres[:-1] if escaped else centres[1:-1]
    xy = np.vstack([np.asarray(start_xy, np.float64).reshape(1, 2), inner,
                    np.asarray(goal_xy, np.float64).reshape(1, 2)])
    return Path.from_points(xy, cost_cells * layer.geometry.resolution_m)


def plan(layer: CostLayer, start_xy: ArrayLike, goal_xy: ArrayLike, *, timeout_s: float = 1.0,
         escape_radius_m: float = 0.5, smooth: bool = True) -> Path:
    """A* path from ``start_xy`` to ``goal_xy`` (world, m) over ``layer``.

    Raises OutsideGrid, StartOccupied, GoalOccupied, NoPath or PlanningTimedOut.
    """
    s, g, escaped = resolve_endpoints(layer, start_xy, goal_xy, escape_radius_m)
    cells, cost_cells = astar_cells(layer.cost, s, g, min_cost=layer.min_cost,
                                    timeout_s=timeout_s)
    return cells_to_path(layer, cells, cost_cells, start_xy, goal_xy, escaped=escaped,
                         smooth=smooth)
