"""The cost layer planners search: lethal cells near obstacles, a decaying margin, cheap skeleton.

Every cell gets a traversal cost multiplier c ≥ ``min_cost`` (∞ = lethal). Moving between
8-neighbours a and b costs ``step · (c_a + c_b) / 2`` with step = 1 or √2 cells, the convention of
``skimage.graph.MCP_Geometric``, which A* here follows too.

With clearance d [m] = distance from a cell's centre to the edge of the nearest obstacle cell
(``(edt_cells − 0.5) · resolution_m``), robot radius r and safety margin m:

    c = ∞                                                  d < r
    c = 1 + w · (exp(−3 (d − r)/m) − e⁻³) / (1 − e⁻³)      r ≤ d < r + m   (w at d = r, 0 at r + m)
    c = 1                                                  d ≥ r + m

then × ``unknown_cost`` on unobserved cells (when they are not obstacles) and × ``skeleton_factor``
on preferred cells (the Voronoi skeleton), see :meth:`CostLayer.with_preferred`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from server.planning.edt_kernel import edt_with_indices
from server.planning.grid import GridGeometry, OccupancyGrid, small_components


@dataclass(frozen=True)
class CostParams:
    """How a grid becomes a cost layer (lengths in metres, costs as multipliers of free space)."""

    robot_radius_m: float = 0.13
    safety_margin_m: float = 0.30
    margin_cost: float = 4.0
    # Unobserved cells (unknown or 40 ≤ p ≤ 70) are obstacles, inflated like walls; when False
    # they are traversable at ``unknown_cost``.
    unknown_is_obstacle: bool = True
    unknown_cost: float = 3.0
    # Unobserved pockets up to this area inside observed space (gaps between LIDAR beams) count
    # as free.
    hole_area_m2: float = 0.1
    skeleton_factor: float = 0.8

    def __post_init__(self) -> None:
        if not 0 < self.skeleton_factor <= 1:
            raise ValueError(f"skeleton_factor must lie in (0, 1], got {self.skeleton_factor}")
        if self.robot_radius_m < 0 or self.safety_margin_m < 0 or self.margin_cost < 0:
            raise ValueError("robot_radius_m, safety_margin_m and margin_cost must be >= 0")
        if self.unknown_cost < 1:
            raise ValueError(f"unknown_cost must be >= 1, got {self.unknown_cost}")


@dataclass(frozen=True, eq=False)
class CostLayer:
    """Per-cell traversal costs of a grid (see the module docstring) with its geometry."""

    cost: NDArray[np.float64]          # (H, W), ∞ = lethal
    clearance_m: NDArray[np.float64]   # (H, W), distance to the nearest obstacle edge
    space: NDArray[np.bool_]           # (H, W), cells that are not obstacles
    geometry: GridGeometry
    min_cost: float                    # lower bound of every finite cost (for A* heuristics)
    # (2, H, W) row/col of the nearest obstacle cell of every cell (the EDT feature transform),
    # shared with the Voronoi skeleton; None when the grid holds no obstacle.
    nearest_obstacle: NDArray[np.intp] | None = None

    @property
    def lethal(self) -> NDArray[np.bool_]:
        return ~np.isfinite(self.cost)

    def with_preferred(self, preferred: NDArray[np.bool_], factor: float) -> CostLayer:
        """A copy whose finite costs on ``preferred`` cells are multiplied by ``factor`` ≤ 1."""
        if preferred.shape != self.cost.shape:
            raise ValueError(f"preferred mask {preferred.shape} != layer {self.cost.shape}")
        cost = np.where(preferred, self.cost * factor, self.cost)
        return replace(self, cost=cost, min_cost=min(self.min_cost, self.min_cost * factor))

    def escape(self, rc: tuple[int, int], radius_m: float) -> tuple[int, int] | None:
        """The non-lethal cell nearest to ``rc`` within ``radius_m`` (``rc`` itself if it is not
        lethal); None if there is none. Ties go to the cell with the larger clearance."""
        r, c = rc
        if np.isfinite(self.cost[r, c]):
            return rc
        k = max(1, math.ceil(radius_m / self.geometry.resolution_m))
        H, W = self.cost.shape
        r0, r1, c0, c1 = max(0, r - k), min(H, r + k + 1), max(0, c - k), min(W, c + k + 1)
        window = np.isfinite(self.cost[r0:r1, c0:c1])
        if not window.any():
            return None
        rr, cc = np.nonzero(window)
        d2 = (rr + r0 - r) ** 2 + (cc + c0 - c) ** 2
        ok = d2 <= k * k
        if not ok.any():
            return None
        rr, cc, d2 = rr[ok], cc[ok], d2[ok]
        best = np.lexsort((-self.clearance_m[rr + r0, cc + c0], d2))[0]
        return int(rr[best] + r0), int(cc[best] + c0)


def obstacle_mask(grid: OccupancyGrid, params: CostParams) -> NDArray[np.bool_]:
    """Cells the robot must keep ``robot_radius_m`` away from."""
    if not params.unknown_is_obstacle:
        return grid.occupied.copy()
    hole_cells = int(params.hole_area_m2 / grid.geometry.cell_area_m2)
    unobserved = grid.unobserved & ~small_components(grid.unobserved, hole_cells)
    return grid.occupied | unobserved


def build_cost_layer(grid: OccupancyGrid, params: CostParams,
                     obstacles: NDArray[np.bool_] | None = None) -> CostLayer:
    """The cost layer of ``grid`` (without skeleton preference), equation in the module doc.

    ``obstacles`` defaults to :func:`obstacle_mask`; pass it when already computed.
    """
    res = grid.resolution_m
    if obstacles is None:
        obstacles = obstacle_mask(grid, params)
    elif obstacles.shape != grid.data.shape:
        raise ValueError(f"obstacle mask {obstacles.shape} != grid {grid.data.shape}")
    space = ~obstacles
    nearest: NDArray[np.intp] | None
    if obstacles.any():
        edt, nearest = edt_with_indices(space)   # scipy's, to the bit, compiled
        clearance = (edt - 0.5) * res
    else:  # no obstacle anywhere: everything is far from one
        clearance, nearest = np.full(grid.data.shape, np.inf), None
    r, m, w = params.robot_radius_m, params.safety_margin_m, params.margin_cost
    cost = np.ones(grid.data.shape, dtype=np.float64)
    if m > 0 and w > 0:
        band = (clearance >= r) & (clearance < r + m)
        e3 = math.exp(-3.0)
        cost[band] += w * (np.exp(-3.0 * (clearance[band] - r) / m) - e3) / (1.0 - e3)
    if not params.unknown_is_obstacle:
        cost[grid.unobserved] *= params.unknown_cost
    cost[clearance < r] = np.inf
    return CostLayer(cost=cost, clearance_m=clearance, space=space, geometry=grid.geometry,
                     min_cost=1.0, nearest_obstacle=nearest)
