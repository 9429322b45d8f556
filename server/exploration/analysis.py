"""Everything one exploration decision derives from the map, computed once per decision."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from schemas.occupancy import UNKNOWN
from server.exploration.frontiers import Frontiers, cluster_frontiers, frontier_mask
from server.exploration.skeleton import SkeletonGraph, skeleton_graph, voronoi_skeleton
from server.exploration.walls import WallMemory
from server.planning.costmap import CostLayer, CostParams, build_cost_layer
from server.planning.grid import OccupancyGrid, small_components


@dataclass(frozen=True)
class AnalysisParams:
    """Map analysis settings (lengths in metres)."""

    cost: CostParams = field(default_factory=CostParams)
    # Voronoi ridge cells need nearest boundary cells at least this far apart (prunes the
    # ridges of a jagged boundary).
    min_separation_m: float = 0.3
    # Frontier clusters shorter than this (counted in cells × resolution) are ignored.
    min_frontier_m: float = 0.3
    # Border of unknown cells kept around the observed part of the grid.
    margin_cells: int = 3
    # Frontier cells this close to a place the robot has already been sent to (a visited
    # target) are not frontiers: standing there did not resolve them, so looking cannot (a
    # wall cleared by grazing beams, a gap too narrow to see through).
    seen_radius_m: float = 1.2


@dataclass(frozen=True, eq=False)
class MapAnalysis:
    """The grid cropped to its observed part, with its cost layer, skeleton and frontiers."""

    grid: OccupancyGrid
    layer: CostLayer               # includes the skeleton preference
    space: NDArray[np.bool_]       # known free space (free cells and small unobserved pockets)
    unexplored: NDArray[np.bool_]  # unobserved cells outside those pockets
    skeleton: NDArray[np.bool_]    # Voronoi ridge cells of the known free space
    frontiers: Frontiers

    @functools.cached_property
    def graph(self) -> SkeletonGraph:
        """The skeleton as a graph (built on first use: a path search needs only the layer)."""
        return skeleton_graph(self.skeleton, clearance=self.layer.clearance_m)


def analyse(grid: OccupancyGrid, params: AnalysisParams,
            include_xy: ArrayLike | None = None,
            seen_xy: ArrayLike | None = None,
            walls_seen: WallMemory | None = None) -> MapAnalysis:
    """Crop to the observed cells (and ``include_xy``, e.g. robot positions), then build the
    cost layer, the Voronoi skeleton of known free space and the frontier clusters (without
    cells within ``params.seen_radius_m`` of the ``seen_xy`` points, e.g. visited targets, and
    away from the cells ``walls_seen`` remembers as walls, as from the current ones)."""
    crop = grid.crop_to_known(params.margin_cells, include_xy=include_xy)
    res = crop.resolution_m
    cp = params.cost
    hole_cells = int(cp.hole_area_m2 / (res * res))
    holes = small_components(crop.unobserved, hole_cells)
    space = crop.free | holes
    unexplored = crop.unobserved & ~holes
    obstacles = crop.occupied | unexplored if cp.unknown_is_obstacle else crop.occupied
    layer = build_cost_layer(crop, cp, obstacles=obstacles)
    # With unknown space as obstacle the layer's feature transform is that of ``space``.
    nearest = layer.nearest_obstacle if cp.unknown_is_obstacle else None
    skeleton = voronoi_skeleton(space, min_separation_cells=params.min_separation_m / res,
                                nearest_boundary=nearest)
    layer = layer.with_preferred(skeleton, cp.skeleton_factor)
    # wall cells: occupied, or observed without a verdict (beams both hit and crossed them)
    walls = crop.occupied | (crop.unobserved & (crop.data != UNKNOWN))
    if walls_seen is not None:
        walls = walls | walls_seen.mask(crop.geometry)
    mask = frontier_mask(space, unexplored & ~walls, walls)
    seen = np.asarray(seen_xy if seen_xy is not None else (), np.float64).reshape(-1, 2)
    if len(seen) and params.seen_radius_m > 0 and mask.any():
        cells = np.argwhere(mask)
        d, _ = cKDTree(seen).query(crop.geometry.cell_to_world(cells),
                                   distance_upper_bound=params.seen_radius_m)
        near = np.isfinite(d)
        mask[cells[near, 0], cells[near, 1]] = False
    frontiers = cluster_frontiers(mask, min_cells=int(np.ceil(params.min_frontier_m / res)))
    return MapAnalysis(crop, layer, space, unexplored, skeleton, frontiers)
