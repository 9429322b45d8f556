"""How well a robot seen by its tag is located, by the tag alone and with the LIDAR fix; prints
JSON.

For each distance, robot r2 is placed facing r1's camera (random bearing within ±0.4 rad,
face turned within ±0.9 rad) in an empty world; the simulator renders r1's camera frame and
casts its 400-beam LIDAR (σ = 8 mm), the agent's OpenCV detector reads the tag, and
``robot_agent.aruco.lidar_fix`` fits the body returns. Errors are against the true centre of
r2 in r1's frame. ``los_kept`` is the share of tag-only sightings that pass the line-of-sight
check on their own range (the agent now checks the fixed range instead).

    python bench/tag_range.py [--samples N] [--distances 2 3 4 5 6 6.8] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

# bench/sim.py would shadow the simulator package: the repository comes first
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from robot_agent.aruco import TagDetector, in_line_of_sight, lidar_fix
from schemas.se2 import wrap_angle
from schemas.tags import CameraMount, TagLayout
from sim.simulator import SimParams, Simulator
from sim.world import World


def facing_pose(layout: TagLayout, mount: CameraMount, distance_m: float, bearing: float,
                turn: float) -> tuple[float, float, float]:
    """r2's pose with its front tag ``distance_m`` from r1's camera at ``bearing``."""
    tx, ty = mount.x_m + distance_m * math.cos(bearing), distance_m * math.sin(bearing)
    heading = bearing + math.pi + turn
    h = layout.mast_half_width_m
    return tx + h * math.cos(heading), ty + h * math.sin(heading), wrap_angle(heading)


def stats(v: list[float]) -> dict[str, float] | None:
    if not v:
        return None
    a = np.asarray(v)
    return {"mean": round(float(a.mean()), 4), "max_abs": round(float(np.abs(a).max()), 4)}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=15)
    ap.add_argument("--distances", type=float, nargs="+", default=[2.0, 3.0, 4.0, 5.0, 6.0, 6.8])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    layout, mount = TagLayout(), CameraMount()
    detector = TagDetector(layout, mount)
    world = World.from_shapes("empty", "bench", [np.array([[50, 50], [51, 50], [51, 51],
                                                           [50, 51.0]])], [])
    params = SimParams()
    lid = params.lidar
    angles = lid.angle_min_rad + lid.angle_increment_rad * np.arange(lid.beams)
    rng = np.random.default_rng(args.seed)
    rows = []
    for dist in args.distances:
        tag_r, tag_b, fix_r, fix_b, los = [], [], [], [], []
        read = fixed = 0
        for k in range(args.samples):
            pose = facing_pose(layout, mount, dist, rng.uniform(-0.4, 0.4),
                               rng.uniform(-0.9, 0.9))
            sim = Simulator(world, {"r1": (0.0, 0.0, 0.0), "r2": pose}, params, seed=k)
            obs = sim.sense()
            frame = obs.frames.get("r1")
            if frame is None:
                continue
            found = detector.detect(frame.image, params.camera.camera.K, "r1").sightings
            if not found:
                continue
            s = found[0]
            read += 1
            true_r, true_b = math.hypot(pose[0], pose[1]), math.atan2(pose[1], pose[0])
            tag_r.append(s.range_m - true_r)
            tag_b.append(math.degrees(wrap_angle(s.bearing_rad - true_b)))
            ranges = obs.ranges_m["r1"]
            los.append(in_line_of_sight(s.range_m, s.bearing_rad, ranges, angles))
            fix = lidar_fix(s.range_m, s.bearing_rad, ranges, angles, params.drive.radius_m)
            if fix is not None:
                fixed += 1
                fix_r.append(fix.range_m - true_r)
                fix_b.append(math.degrees(wrap_angle(fix.bearing_rad - true_b)))
        rows.append({"distance_m": dist, "samples": args.samples, "tags_read": read,
                     "lidar_fixed": fixed, "tag_range_error_m": stats(tag_r),
                     "tag_bearing_error_deg": stats(tag_b),
                     "fix_range_error_m": stats(fix_r), "fix_bearing_error_deg": stats(fix_b),
                     "los_kept": round(sum(los) / len(los), 3) if los else None})
    fix_max_r = max((r["fix_range_error_m"]["max_abs"] for r in rows if r["fix_range_error_m"]),
                    default=None)
    fix_max_b = max((r["fix_bearing_error_deg"]["max_abs"] for r in rows
                     if r["fix_bearing_error_deg"]), default=None)
    out = {"distances": rows, "fix_range_error_max_m": fix_max_r,
           "fix_bearing_error_max_deg": fix_max_b,
           "tag_range_error_max_m": max((r["tag_range_error_m"]["max_abs"] for r in rows
                                         if r["tag_range_error_m"]), default=None)}
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
