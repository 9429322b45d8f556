"""A known map surveyed from the truth: LIDAR scans taken at known poses all over a world.

For worlds too large to explore in a benchmark's time (the ambiguous wings: 36 rooms), the map
robots are placed in is made as a survey would make it: scans at poses on a lattice of the
free space, each kept as a keyframe at its true pose, in the world's frame. The robots placed
in it then see the same building as the map, as they would a map made by exploring it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

from schemas.occupancy import FREE
from server.knownmap.mapdata import KnownMap
from server.slam.config import SlamConfig
from server.slam.keyframes import Keyframe
from server.slam.sensor import scan_points
from sim.loader import load_world
from sim.raycast import RayCaster
from sim.simulator import LidarSpec
from sim.world_map import world_map

F64 = NDArray[np.float64]


def survey_map(world_path: Path, spacing_m: float = 1.5, clearance_m: float = 0.4,
               seed: int = 0, resolution_m: float = 0.1) -> KnownMap:
    """Keyframes of scans at lattice poses ``spacing_m`` apart in the world's free space
    (at least ``clearance_m`` from walls), in the world frame."""
    world = load_world(world_path)
    grid, _ = world_map(world_path, 0.05)
    clear = distance_transform_edt(grid.cells == FREE) * grid.resolution_m >= clearance_m
    step = max(1, round(spacing_m / grid.resolution_m))
    rows, cols = np.nonzero(clear)
    keep = (rows % step == 0) & (cols % step == 0)
    xs = grid.origin[0] + (cols[keep] + 0.5) * grid.resolution_m
    ys = grid.origin[1] + (rows[keep] + 0.5) * grid.resolution_m
    rng = np.random.default_rng(seed)
    lid = LidarSpec()
    caster = RayCaster(world.segments, world.circles)
    cfg = SlamConfig()
    angles = lid.angle_min_rad + lid.angle_increment_rad * np.arange(lid.beams)
    kfs: list[Keyframe] = []
    poses = []
    for x, y in zip(xs, ys, strict=True):
        th = float(rng.uniform(-math.pi, math.pi))
        true = caster.cast((float(x), float(y), th), lid.beams, lid.angle_min_rad,
                           lid.angle_increment_rad, lid.cast_range_m)
        ranges = lid.noisy(true, rng)
        scan = scan_points(ranges, angles, cfg.scan, cfg.scan.normal_window,
                           min(cfg.scan.no_return_free_m, lid.range_max_m))
        kfs.append(Keyframe.create(len(kfs), len(kfs) * 10**8, scan, np.zeros(3)))
        poses.append((float(x), float(y), th))
    return KnownMap(kfs, np.array(poses), ["survey"] * len(kfs), resolution_m, "survey", 1,
                    {"made": f"surveyed from the truth every {spacing_m} m"})
