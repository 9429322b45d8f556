"""The seam between ``RobotSlam``'s pipeline and a sensor's handling: which model a scan goes
to, and the narrow model's parts on small problems with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.slam.config import GraphConfig, SlamConfig, SquareWallsConfig
from server.slam.errors import SlamInputError
from server.slam.frontend import FrontendMatch, MatchKind
from server.slam.heading_ties import HeadingTies
from server.slam.narrow import NarrowSensor, sensor_choice
from server.slam.robot import RobotSlam
from server.slam.sensor import LidarSensor
from server.slam.smoothing import RecentMatches

WIDE = -math.pi + 2 * math.pi * np.arange(400) / 400
NARROW = np.linspace(-math.radians(43.5), math.radians(43.5), 160)


def room(angles_rad: np.ndarray) -> np.ndarray:
    """Ranges [m] from the middle of a 4 m × 4 m room."""
    return np.minimum(2.0 / np.maximum(np.abs(np.cos(angles_rad)), 1e-9),
                      2.0 / np.maximum(np.abs(np.sin(angles_rad)), 1e-9))


def test_each_scan_goes_to_the_model_its_field_of_view_calls_for() -> None:
    choice = sensor_choice(SlamConfig())
    assert isinstance(choice.for_angles(WIDE), LidarSensor)
    assert isinstance(choice.for_angles(NARROW), NarrowSensor)
    # the threshold is the configuration's: under 1°, the camera's scans are wide ones
    wide_only = sensor_choice(SlamConfig.model_validate({"matcher": {"narrow_fov_deg": 1.0}}))
    assert isinstance(wide_only.for_angles(NARROW), LidarSensor)
    # the two share one set of square walls, which the LIDAR's keyframes join only on request
    assert isinstance(choice.wide, LidarSensor) and choice.wide.ties is None
    both = sensor_choice(SlamConfig.model_validate({"square_walls": {"narrow_only": False}}))
    assert isinstance(both.wide, LidarSensor) and isinstance(both.narrow, NarrowSensor)
    assert both.wide.ties is both.narrow.ties


def test_the_robot_follows_its_latest_scan_and_bad_input_changes_nothing() -> None:
    slam = RobotSlam("a", SlamConfig())
    assert not slam.narrow and not slam.sweep_due(0)
    slam.add_scan(0, (0.0, 0.0, 0.0), room(NARROW), NARROW)
    assert slam.narrow and isinstance(slam.sensor, NarrowSensor)
    assert slam.sweep_due(100_000_000)       # a camera stands still at its start
    with pytest.raises(SlamInputError):      # ranges and angles of different lengths
        slam.add_scan(200_000_000, (0.0, 0.0, 0.0), room(WIDE)[:10], WIDE)
    assert slam.narrow and slam.stats.scans == 1
    slam.add_scan(300_000_000, (0.0, 0.0, 0.0), room(WIDE), WIDE)
    assert not slam.narrow and not slam.sweep_due(400_000_000) and slam.stats.scans == 2


def match_at(x_m: float, kind: MatchKind = MatchKind.ICP) -> FrontendMatch:
    return FrontendMatch(np.array([x_m, 0.0, 0.0]), kind, np.diag([1e4, 1e4, 1e6]), 0.9)


def test_equal_matches_at_one_place_average_to_their_mean() -> None:
    recent = RecentMatches(keep=10)
    anchor = np.zeros(3)

    def smoothed(m: FrontendMatch) -> FrontendMatch:
        return recent.smoothed(m, np.zeros(3), 7, anchor, lambda key: anchor, GraphConfig())

    first = match_at(0.0)
    assert smoothed(first) is first             # one match: itself
    got = smoothed(match_at(0.1))
    assert got.T_map_robot == pytest.approx([0.05, 0.0, 0.0], abs=1e-9)
    assert got.kind == MatchKind.ICP
    odometry = match_at(0.3, MatchKind.ODOMETRY)
    assert smoothed(odometry) is odometry       # odometry's pose is not averaged, nor kept
    assert len(recent.matches) == 2
    # the keyframe they were kept after moved: so do they
    anchor[:] = (1.0, 0.0, 0.0)
    assert smoothed(match_at(1.2)).T_map_robot[0] == pytest.approx(1.1, abs=1e-9)
    recent.clear()
    assert smoothed(match_at(0.0)).T_map_robot[0] == 0.0


def test_only_a_whole_scan_taken_where_the_robot_started_is_the_walls_reference() -> None:
    a = math.radians(10.0) + np.arange(200) % 4 * math.pi / 2     # square walls, turned 10°
    normals = np.stack([np.cos(a), np.sin(a)], axis=1)
    start = np.array([1.0, 2.0, 0.3])
    moved = HeadingTies(SquareWallsConfig())
    moved.set_reference(normals, start, start + np.array([0.01, 0.0, 0.0]), 0.005, 0.5)
    assert moved.reference is None
    ties = HeadingTies(SquareWallsConfig())
    ties.set_reference(normals, start, start + np.array([0.001, 0.0, 0.004]), 0.005, 0.5)
    # in keyframe 0's frame: the scan's direction plus the 0.004 rad the robot turned since
    assert ties.reference is not None and ties.reference[0] == 0
    assert ties.reference[1] == pytest.approx(math.radians(10.0) + 0.004, abs=1e-9)
