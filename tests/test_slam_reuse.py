"""Keyframes re-used where a robot passes again (``slam.keyframes.reuse``): laps of the same
loop after the first add next to no keyframes, and the robot stays where the truth is."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.se2 import between, pose_distance
from server.slam import RobotSlam, SlamConfig
from tests.test_slam_synthetic import align_error, drive, ring_world, waypoints_path

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

LOOP = [(1.0, 1.0), (13.0, 1.0), (13.0, 9.0), (1.0, 9.0), (1.0, 1.0)]


def laps(slam: RobotSlam, n: int, reuse_after_first: bool) -> tuple[np.ndarray, list[int]]:
    """Drive the ring corridor ``n`` times; returns the truth and keyframes after each lap."""
    one = waypoints_path(LOOP, 0.1)
    truth = np.concatenate([one] + [one[1:]] * (n - 1))
    d = drive(ring_world(), truth, odom_drift_rad_per_m=0.01, odom_scale=1.02, seed=2)
    per_lap, counts = len(one) - 1, []
    for i, (odom, ranges) in enumerate(zip(d.odom, d.ranges, strict=True)):
        if i and i % per_lap == 0:
            counts.append(len(slam.keyframes))
            slam.reusing = reuse_after_first
        slam.add_scan(1_000_000_000 + i * 100_000_000, odom, ranges, d.angles)
    counts.append(len(slam.keyframes))
    return truth, counts


def test_laps_over_mapped_ground_reuse_keyframes_and_stay_on_the_truth() -> None:
    slam = RobotSlam("a", SlamConfig())
    truth, counts = laps(slam, 3, reuse_after_first=True)
    first = counts[0]
    assert first > 60
    assert counts[-1] - first < 0.1 * first, counts        # laps 2 and 3: < 10 % more
    assert slam.stats.reused > first                         # ... as each re-used keyframes
    # once per 0.5 m or 20° of motion, as keyframes would be, not at every scan
    assert slam.stats.reused < 0.35 * (len(truth) - len(truth) // 3)
    _, poses = slam.scan_poses()
    err = align_error(poses, truth)
    assert err.max() < 0.1, err.max()
    # the pose right now (the map frame is the first pose's), not only the trajectory
    assert pose_distance(between(between(truth[0], truth[-1]), slam.pose))[0] < 0.1


def test_without_reuse_every_lap_adds_its_keyframes() -> None:
    slam = RobotSlam("a", SlamConfig())
    _, counts = laps(slam, 2, reuse_after_first=False)
    assert counts[1] > 1.8 * counts[0], counts
    assert slam.stats.reused == 0
