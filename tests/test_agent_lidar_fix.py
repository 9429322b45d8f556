"""The LIDAR fix of a tag sighting: real renders through the real detector, the simulator's
LIDAR returns off the observed robot's body."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot_agent.aruco import Sighting, TagDetector, lidar_fix
from schemas.se2 import wrap_angle
from sim.simulator import Observation, SimParams, Simulator
from sim.world import World
from tests.test_sim_camera import LAYOUT, MOUNT, empty, facing_pose


def angles(sim: Simulator) -> np.ndarray:
    lid = sim.p.lidar
    return lid.angle_min_rad + lid.angle_increment_rad * np.arange(lid.beams)


def sighted(world: World, distance_m: float, seed: int
            ) -> tuple[Simulator, tuple[float, float, float], Observation, list[Sighting]]:
    rng = np.random.default_rng(seed)
    pose = facing_pose(distance_m, rng.uniform(-0.4, 0.4), rng.uniform(-0.9, 0.9))
    sim = Simulator(world, {"r1": (0.0, 0.0, 0.0), "r2": pose}, SimParams(), seed=seed)
    obs = sim.sense()
    frame = obs.frames["r1"]
    found = TagDetector(LAYOUT, MOUNT).detect(frame.image, sim.p.camera.camera.K, "r1")
    return sim, pose, obs, found.sightings


@pytest.mark.parametrize("distance_m", [3.0, 4.5, 6.0])
def test_far_sightings_get_the_lidar_range_and_bearing(distance_m: float) -> None:
    radius = SimParams().drive.radius_m
    tag_err, fix_err, bearing_err = [], [], []
    for seed in range(8):
        sim, pose, obs, sightings = sighted(empty(), distance_m, seed)
        if not sightings:
            continue
        s = sightings[0]
        true_r, true_b = math.hypot(pose[0], pose[1]), math.atan2(pose[1], pose[0])
        fix = lidar_fix(s.range_m, s.bearing_rad, obs.ranges_m["r1"], angles(sim), radius)
        assert fix is not None and fix.beams >= 2
        tag_err.append(abs(s.range_m - true_r))
        fix_err.append(abs(fix.range_m - true_r))
        bearing_err.append(abs(math.degrees(wrap_angle(fix.bearing_rad - true_b))))
        # the reported σ covers the error
        assert abs(fix.range_m - true_r) <= 3 * fix.sigma_range_m
        assert fix.sigma_range_m < s.sigma_range_m
    assert len(fix_err) >= 3
    assert max(fix_err) <= 0.03 and max(bearing_err) <= 0.35
    if distance_m >= 4.5:   # where the tag's own range is biased, the LIDAR's is not
        assert np.mean(tag_err) > 2 * np.mean(fix_err)


def test_no_fix_where_the_lidar_sees_no_robot() -> None:
    radius = SimParams().drive.radius_m
    sim, _, obs, sightings = sighted(empty(), 4.0, 1)
    s = sightings[0]
    ranges = obs.ranges_m["r1"]
    # a view placed a metre off, or half a metre across the line of sight: nothing there
    assert lidar_fix(s.range_m + 1.0, s.bearing_rad, ranges, angles(sim), radius) is None
    assert lidar_fix(s.range_m, s.bearing_rad + 0.5 / s.range_m, ranges, angles(sim),
                     radius) is None
    # no radius given: no fix
    assert lidar_fix(s.range_m, s.bearing_rad, ranges, angles(sim), 0.0) is None
    assert lidar_fix(s.range_m, s.bearing_rad, ranges, angles(sim), radius) is not None


def test_a_wall_right_behind_the_robot_does_not_pull_the_fit() -> None:
    radius = SimParams().drive.radius_m
    rng = np.random.default_rng(5)
    for seed in range(4):
        pose = facing_pose(5.0, rng.uniform(-0.2, 0.2), 0.0)
        x = pose[0] + 0.4                       # a wall 0.27 m behind the robot's back
        wall = World.from_shapes("wall", "test", [np.array([[x, -6.0], [x + 0.1, -6.0],
                                                            [x + 0.1, 6.0], [x, 6.0]])], [])
        sim = Simulator(wall, {"r1": (0.0, 0.0, 0.0), "r2": pose}, SimParams(), seed=seed)
        obs = sim.sense()
        found = TagDetector(LAYOUT, MOUNT).detect(obs.frames["r1"].image,
                                                  sim.p.camera.camera.K, "r1")
        s = found.sightings[0]
        fix = lidar_fix(s.range_m, s.bearing_rad, obs.ranges_m["r1"], angles(sim), radius)
        assert fix is not None
        assert abs(fix.range_m - math.hypot(pose[0], pose[1])) <= 0.03
