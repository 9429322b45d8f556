"""One valid instance of every message type, for round-trip, fuzz and bus tests."""

from __future__ import annotations

import numpy as np

from schemas import (
    Event,
    Hypothesis,
    MapUpdate,
    Message,
    RobotEstimate,
    RobotStates,
    RobotStatus,
    Scan,
    SimClock,
    SimGroundTruth,
    SimImage,
    SimLidar,
    SimMotorCommand,
    SimOdometry,
    SimStepAck,
    TagDetection,
    TagDetections,
    TeamCoverage,
    TruePose,
    TrueRelative,
    VelocityCommand,
    quantise_ranges_mm,
)

STAMP = 1_700_000_000_123_456_789


def scan(robot_id: str = "r1", n: int = 400, seq: int = 7, seed: int = 0) -> Scan:
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.05, 10.0, n)
    ranges[::37] = np.inf  # some no-returns
    return Scan(robot_id=robot_id, seq=seq, stamp_ns=STAMP, odom_pose=(1.25, -3.5, 0.3),
                angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / n, range_min_mm=50,
                range_max_mm=10000, ranges_mm=quantise_ranges_mm(ranges, 0.05, 10.0))


def all_examples() -> dict[str, Message]:
    grid = np.full((40, 60), -1, np.int8)
    grid[10:20, 10:50] = 0
    grid[9, 10:50] = 100
    lidar = scan()
    return {
        "Scan": lidar,
        "TagDetections": TagDetections(robot_id="r1", seq=3, stamp_ns=STAMP, detections=[
            TagDetection(tag_id=5, observed_robot_id="r2", range_m=1.5, bearing_rad=0.1,
                         yaw_rad=3.0, sigma_range_m=0.02, sigma_bearing_rad=0.01,
                         sigma_yaw_rad=0.05, reprojection_error_px=0.3)]),
        "RobotStatus": RobotStatus(robot_id="r1", seq=1, stamp_ns=STAMP, state="ok",
                                   battery_v=12.1, cpu_percent=4.5, rss_mb=60.0, scans_sent=10),
        "VelocityCommand": VelocityCommand(robot_id="r1", seq=2, stamp_ns=STAMP, v_mps=0.3,
                                           omega_rps=-0.5, ttl_s=0.5),
        "MapUpdate": MapUpdate.from_grid(grid, seq=4, stamp_ns=STAMP, team_id="t1",
                                         robot_ids=["r1", "r2"], resolution_m=0.05,
                                         origin=(-1.5, -1.0, 0.0)),
        "RobotStates": RobotStates(seq=5, stamp_ns=STAMP, robots=[
            RobotEstimate(robot_id="r1", team_id="t1", pose=(1.0, 2.0, 0.5), mode="exploring",
                          target=(3.0, 4.0), distance_m=12.5, keyframes=40),
            RobotEstimate(robot_id="r2", team_id="t2", pose=(0.5, 0.0, 0.1),
                          localisation="searching",
                          hypotheses=[Hypothesis(pose=(4.0, 5.0, 1.5), strength=150.0),
                                      Hypothesis(pose=(-4.0, 5.0, -1.5), strength=120.0)])],
            teams=[TeamCoverage(team_id="t1", robot_ids=["r1"], coverage=0.4,
                                explored_m2=160.0)]),
        "Event": Event(seq=6, stamp_ns=STAMP, kind="merge", robot_ids=["r1", "r2"],
                       team_id="t1", message="merged", transform=(1.0, 2.0, 0.1),
                       covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.001]),
        "SimClock": SimClock(seq=7, stamp_ns=100_000_000, step=1, dt_ns=100_000_000,
                             lockstep=True),
        "SimLidar": SimLidar(robot_id="r1", seq=8, stamp_ns=STAMP,
                             angle_min_rad=lidar.angle_min_rad,
                             angle_increment_rad=lidar.angle_increment_rad, range_min_mm=50,
                             range_max_mm=10000, ranges_mm=lidar.ranges_mm, lockstep=True),
        "SimOdometry": SimOdometry(robot_id="r1", seq=9, stamp_ns=STAMP, pose=(0.1, 0.2, 0.3),
                                   v_mps=0.3, omega_rps=0.1),
        "SimImage": SimImage(robot_id="r1", seq=10, stamp_ns=STAMP, width=8, height=6, fx=500.0,
                             fy=500.0, cx=4.0, cy=3.0, data=bytes(range(48))),
        "SimMotorCommand": SimMotorCommand(robot_id="r1", seq=11, stamp_ns=STAMP, v_mps=0.2,
                                           omega_rps=0.0),
        "SimStepAck": SimStepAck(robot_id="r1", seq=12, stamp_ns=STAMP, step=12, v_mps=0.25,
                                 omega_rps=-0.4),
        "SimGroundTruth": SimGroundTruth(seq=13, stamp_ns=STAMP, poses=[
            TruePose(robot_id="r1", pose=(1.0, 1.0, 0.0), collisions=0, distance_m=3.0)],
            relatives=[TrueRelative(observer_id="r1", observed_id="r2", tag_id=4,
                                    relative_pose=(1.5, 0.0, 3.14), image_seq=10)],
            world="house_small.world"),
    }
