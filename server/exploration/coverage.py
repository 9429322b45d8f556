"""Coverage: how much of the environment the map has explored.

A cell counts as explored when it is classified free (p < 0.4) or occupied (p > 0.7); unknown
cells and uncertain ones (0.4 ≤ p ≤ 0.7) do not. Coverage = explored cells × cell area / the
environment's total area, not clipped at 1 (a map that marks space outside the real environment
as explored can exceed it).
"""

from __future__ import annotations

from server.planning.grid import OccupancyGrid


def explored_area_m2(grid: OccupancyGrid) -> float:
    """Explored cells × resolution² [m²]."""
    return float((grid.free | grid.occupied).sum()) * grid.geometry.cell_area_m2


def coverage(grid: OccupancyGrid, total_area_m2: float) -> float:
    """explored_area_m2 / total_area_m2 (dimensionless)."""
    if not total_area_m2 > 0:
        raise ValueError(f"total_area_m2 must be > 0, got {total_area_m2}")
    return explored_area_m2(grid) / total_area_m2


def coverage_reached(grid: OccupancyGrid, total_area_m2: float, threshold: float) -> bool:
    return coverage(grid, total_area_m2) >= threshold
