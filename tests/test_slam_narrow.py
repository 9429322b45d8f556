"""SLAM and steering with a narrow, short scan: a depth camera turned on a tower in the small
house, alone and beside a LIDAR teammate; and the reactive layer's memory of what it saw."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from bench.support.mission import scan_of
from schemas.occupancy import OCCUPIED, UNKNOWN
from schemas.se2 import between
from server.command.steering import ObstacleMemory, mapped_obstacles
from server.config import ServerConfig
from server.core import ServerCore
from server.planning import OccupancyGrid as PlanningGrid
from server.slam.config import MatcherConfig
from server.slam.frontend import is_narrow, min_points
from server.slam.keyframes import gather
from server.slam.scan import scan_to_points
from sim.config import SimConfig
from sim.loader import load_world
from sim.process import params_from_config
from sim.simulator import Simulator
from tests.test_team_merge import WORLD

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

SPAWN = {"r1": (-8.0, 9.0, 0.0), "r2": (-3.0, 9.0, 3 * math.pi / 2)}


def test_a_narrow_scan_knows_its_field_of_view() -> None:
    a = np.linspace(1.0, 2.5, 160)
    s = scan_to_points(np.full(160, 2.0), a, 0.05, 40.0)
    assert s.fov_rad == pytest.approx(1.5 + 1.5 / 159) and s.heading_rad == pytest.approx(1.75)
    cfg = MatcherConfig()
    assert is_narrow(s, cfg) and min_points(s, cfg) == cfg.narrow_min_points
    wide = scan_to_points(np.full(400, 2.0), np.linspace(-math.pi, math.pi, 400,
                                                         endpoint=False), 0.05, 40.0)
    assert not is_narrow(wide, cfg) and min_points(wide, cfg) == cfg.min_points


def run(sensors: dict[str, str], seconds: float, slam: dict[str, Any] | None = None,
        seed: int = 0, true_poses: dict[tuple[str, int], np.ndarray] | None = None
        ) -> tuple[ServerCore, dict[str, float]]:
    """The robots exploring the small house from known starts (one team); the largest error
    of each robot's pose against the truth, in its own start frame. ``true_poses``, if given,
    receives each robot's true pose at each scan's stamp."""
    spawn = {r: SPAWN[r] for r in sorted(sensors)}
    cfg = ServerConfig.model_validate({
        "robots": sorted(spawn), "slam": {"grid": {"resolution_m": 1 / 15}, **(slam or {})},
        "explore": {"total_area_m2": 400.0, "coverage_threshold": 0.98},
        "teams": {"start_poses": {r: list(p) for r, p in spawn.items()}}})
    core = ServerCore(cfg)
    sim = Simulator(load_world(WORLD), spawn,
                    params_from_config(SimConfig(), {r: k for r, k in sensors.items()}), seed)
    worst = dict.fromkeys(spawn, 0.0)
    for _ in range(round(seconds / 0.1)):
        obs = sim.sense()
        for rid in spawn:
            if true_poses is not None:
                true_poses[rid, obs.stamp_ns] = np.array(sim.robots[rid].pose)
            cmd = core.on_scan(scan_of(sim, obs, rid))
            sim.set_command(rid, cmd.v_mps, cmd.omega_rps)
            truth = between(np.array(spawn[rid]), np.array(sim.robots[rid].pose))
            est = core.fleet.robots[rid].slam
            own = between(est.keyframe_poses()[0], est.pose)   # from its first keyframe
            worst[rid] = max(worst[rid], math.hypot(*(own[:2] - truth[:2])))
        sim.advance()
    return core, worst


def test_a_depth_robot_alone_keeps_its_pose_where_treating_its_scans_as_wide_loses_it() -> None:
    core, worst = run({"r1": "depth"}, 60.0)
    s = core.fleet.robots["r1"].slam.stats
    assert worst["r1"] < 0.2, worst
    assert s.matches["icp"] + s.matches["degenerate"] > 2 * s.matches["odometry"], s
    # the same robot with its scans taken for 360° ones (no narrow handling at all)
    _, wide = run({"r1": "depth"}, 60.0, {"matcher": {"narrow_fov_deg": 1.0}})
    assert wide["r1"] > 2 * worst["r1"], (wide, worst)


def test_a_depth_robot_matches_against_its_lidar_teammates_map() -> None:
    core, worst = run({"r1": "lidar", "r2": "depth"}, 40.0)
    r1, r2 = core.fleet.robots["r1"].slam, core.fleet.robots["r2"].slam
    assert r2.graph is r1.graph and r2.narrow and not r1.narrow
    local = r2.local_map
    assert local is not None
    own, _ = gather(r2.keyframes, r2.keyframe_poses())
    mate, _ = gather(r1.keyframes, r1.keyframe_poses())
    from scipy.spatial import cKDTree
    d_own, _ = cKDTree(own).query(local.points)
    d_mate, _ = cKDTree(mate).query(local.points)
    # walls only the LIDAR robot saw are in the depth robot's local map
    assert np.sum((d_own > 0.5) & (d_mate < 0.05)) > 50
    # the depth robot drifts where its teammate has not been, but no more than it would
    # alone (a map in the wrong frame, say, would throw it off by metres)
    assert worst["r1"] < 0.05 and worst["r2"] < 0.4, worst


def test_obstacle_memory_carries_what_was_seen_with_the_robot() -> None:
    mem = ObstacleMemory()
    wall = np.array([[1.0, 0.0], [1.0, 0.5]])
    out = mem.around(0, np.zeros(3), wall, keep_s=5.0)
    assert np.allclose(out, wall)
    # the robot turned half round and moved back 0.5 m; its camera now sees nothing
    pose = np.array([-0.5, 0.0, math.pi])
    out = mem.around(1_000_000_000, pose, np.zeros((0, 2)), keep_s=5.0)
    assert np.allclose(out, [[-1.5, 0.0], [-1.5, -0.5]])   # the wall is behind it now
    assert len(mem.around(7_000_000_000, pose, np.zeros((0, 2)), keep_s=5.0)) == 0  # too old
    mem.around(8_000_000_000, pose, wall, keep_s=5.0)
    # a clock that steps back forgets what came "later"
    assert len(mem.around(2_000_000_000, pose, np.zeros((0, 2)), keep_s=5.0)) == 0


def test_a_narrow_robot_avoids_the_mapped_walls_right_around_it() -> None:
    """A wall corner beside the robot that its camera, turned elsewhere, has not shown lately
    is still in the team's map: the reactive layer gets its cells within the radius."""
    data = np.zeros((40, 40), dtype=np.int8)        # 2 m × 2 m at 5 cm, origin (-1, -1)
    data[:, 30] = OCCUPIED                           # a wall along x = 0.525
    data[0, 0] = UNKNOWN
    grid = PlanningGrid(data, 0.05, (-1.0, -1.0))
    pose = np.array([0.0, 0.0, math.pi / 2])         # facing +y: the wall is on its right
    pts = mapped_obstacles(grid, pose, 1.0)
    assert len(pts) > 20 and np.all(np.hypot(*pts.T) <= 1.0)
    assert np.allclose(pts[:, 1], -0.525)            # to its right, in its body frame
    assert len(mapped_obstacles(grid, pose, 0.5)) == 0       # the wall is farther than that
    assert len(mapped_obstacles(None, pose, 1.0)) == 0
    assert len(mapped_obstacles(grid, np.array([9.0, 9.0, 0.0]), 1.0)) == 0   # off the map
