"""``mrslam world-map``: a world's ground-truth occupancy map (nav2 files) and its free area.

The free area is the free space enclosed by the world's obstacles: free cells 4-connected to
the border of the map (the outside of the building) are excluded and written as unknown. It is
what exploration can cover. Tiny enclosed pockets (e.g. between overlapping wall boxes) count
too; ``largest_region_m2`` is the biggest connected free region alone.

Exploration coverage counts a cell as explored when the map marks it free or occupied, so the
"total area" for a coverage threshold is ``explorable_area_m2``: the free area plus the wall
faces bounding it (occupied cells next to free ones, ``wall_face_area_m2``). Against the free
area alone, the walls a map has seen would count as explored area that is not there, and a
threshold would be reached with several percent of the free space unseen (about 6 % in an
office of 0.1 m walls).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from schemas.occupancy import FREE, OCCUPIED, UNKNOWN
from sim.grid import free_regions, rasterise, wall_face_area_m2, write_nav2
from sim.loader import load_world


def world_map(world_path: str | Path, resolution_m: float = 0.05, lidar_height_m: float = 0.2,
              model_path: list[str | Path] | None = None) -> tuple[Any, dict[str, Any]]:
    """(grid, figures) for a world file."""
    world = load_world(world_path, model_path, lidar_height_m)
    grid = rasterise(world, resolution_m)
    regions = free_regions(grid)
    xmin, ymin, xmax, ymax = world.bounds()
    figures = {
        "world": str(world_path),
        "resolution_m": resolution_m,
        "free_area_m2": round(grid.area_m2(FREE), 3),
        "wall_face_area_m2": round(wall_face_area_m2(grid), 3),
        "explorable_area_m2": round(grid.area_m2(FREE) + wall_face_area_m2(grid), 3),
        "largest_region_m2": round(regions[0], 3) if regions else 0.0,
        "free_regions": len(regions),
        "occupied_area_m2": round(grid.area_m2(OCCUPIED), 3),
        "exterior_area_m2": round(grid.area_m2(UNKNOWN), 3),
        "bounds_m": [round(v, 4) for v in (xmin, ymin, xmax, ymax)],
        "bbox_m2": round((xmax - xmin) * (ymax - ymin), 3),
        "grid_cells": list(grid.shape),
    }
    return grid, figures


def run(world: str | Path, resolution: float = 0.05, out: str | Path = "world-map",
        lidar_height_m: float = 0.2) -> dict[str, Any]:
    """Write ``map.pgm``/``map.png``/``map.yaml`` and ``area.json`` into ``out``; return the
    figures (the CLI prints them)."""
    if not resolution > 0:
        raise ValueError(f"--resolution must be > 0, got {resolution}")
    grid, figures = world_map(world, resolution, lidar_height_m)
    out = Path(out)
    write_nav2(grid, out)
    figures["map"] = str(out / "map.yaml")
    (out / "area.json").write_text(json.dumps(figures, indent=2) + "\n")
    return figures
