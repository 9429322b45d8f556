"""Path planning on occupancy grids: cost layer, A*, one-to-many Dijkstra, shortcutting.

    layer = build_cost_layer(grid, CostParams())            # lethal / margin / free costs
    path = plan(layer, start_xy, goal_xy)                    # A*, typed PlanningError subclasses
    field = CostField(layer, start_xy); field.costs_m(goals)  # many goals from one start
"""

from server.planning.astar import astar_cells, plan
from server.planning.costmap import CostLayer, CostParams, build_cost_layer, obstacle_mask
from server.planning.dijkstra import CostField
from server.planning.errors import (
    GoalOccupied,
    NoPath,
    OutsideGrid,
    PlanningError,
    PlanningTimedOut,
    StartOccupied,
)
from server.planning.grid import GridError, GridGeometry, OccupancyGrid
from server.planning.path import Path, polyline_length_m, shortcut_cells

__all__ = [
    "CostField",
    "CostLayer",
    "CostParams",
    "GoalOccupied",
    "GridError",
    "GridGeometry",
    "NoPath",
    "OccupancyGrid",
    "OutsideGrid",
    "Path",
    "PlanningError",
    "PlanningTimedOut",
    "StartOccupied",
    "astar_cells",
    "build_cost_layer",
    "obstacle_mask",
    "plan",
    "polyline_length_m",
    "shortcut_cells",
]
