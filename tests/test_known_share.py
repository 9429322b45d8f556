"""Which of another team's keyframes can test a transform on a map: those whose points' near
side the map knows (``server.rendezvous.maps.known_share``)."""

from __future__ import annotations

import math

import numpy as np

from schemas.se2 import between, compose
from server.rendezvous.maps import cross_matches, known_share
from server.slam import RobotSlam, SlamConfig
from server.slam.grid import GridParams, OccupancyGrid
from tests.test_slam_synthetic import Segment, box, drive, waypoints_path


def wall_points(x: float, y0: float, y1: float, n: int = 60) -> np.ndarray:
    return np.c_[np.full(n, x), np.linspace(y0, y1, n)]


def room_a() -> OccupancyGrid:
    """Team a's map: a robot at the origin saw a wall at x = 2 m, from its west side, many
    times; nothing east of the wall."""
    grid = OccupancyGrid(GridParams(resolution_m=0.05, padding_m=1.0))
    for _ in range(3):
        grid.insert_scan(np.zeros(3), wall_points(2.0, -1.5, 1.5))
    return grid


def test_a_wall_seen_from_the_same_side_is_known_and_from_behind_is_not() -> None:
    share = known_share(room_a())
    # b stands west of the wall too, 1 m from it, and sees it: a's map knows that side
    west = wall_points(1.0, -1.0, 1.0)
    assert share(west, np.array([1.0, 0.0, 0.0])) > 0.9
    # the same scan, turned: b is placed at x = 3 m facing west, so it sees the wall from the
    # east side, which a's map never saw (a's room is beyond it): not a test
    east = wall_points(1.0, -1.0, 1.0)
    assert share(east, np.array([3.0, 0.0, math.pi])) < 0.2
    # a room a never looked into at all
    assert share(west, np.array([6.0, 5.0, 0.0])) == 0.0


def test_a_wrong_placement_in_known_space_stays_a_test() -> None:
    """A wall placed in the middle of a's room by a wrong transform: its near side is the
    room's free floor, which a's map knows, so the keyframe is tried (and fails to match)."""
    share = known_share(room_a())
    wall = wall_points(0.8, -1.0, 1.0)          # 0.8 m ahead of b, placed at x = 0.2 m
    # (the ends lie outside the fan of floor a's robot saw): above the 0.5 a match needs
    assert share(wall, np.array([0.2, 0.0, 0.0])) > 0.7


def test_no_points_or_an_empty_map_know_nothing() -> None:
    share = known_share(room_a())
    assert share(np.zeros((0, 2)), np.zeros(3)) == 0.0
    empty = known_share(OccupancyGrid(GridParams()))
    assert empty(wall_points(1.0, -1.0, 1.0), np.zeros(3)) == 0.0


def two_rooms() -> list[Segment]:
    """Two rooms a wall apart (x = 5 m), unlike inside: a pillar in the west one, an alcove
    in the east one, and a door between them at the north end (closed here)."""
    west = box(0.0, 0.0, 5.0, 4.0) + box(1.5, 1.0, 2.0, 1.5)
    east = [((5.0, 0.0), (10.0, 0.0)), ((10.0, 0.0), (10.0, 2.5)), ((10.0, 2.5), (10.8, 2.5)),
            ((10.8, 2.5), (10.8, 4.0)), ((10.8, 4.0), (5.0, 4.0))]
    return west + east


def robot_in(walls: list[Segment], path: list[tuple[float, float]],
             name: str) -> tuple[RobotSlam, np.ndarray]:
    truth = waypoints_path(path, 0.2)
    d = drive(walls, truth, odom_drift_rad_per_m=0.0, odom_scale=1.0)
    slam = RobotSlam(name, SlamConfig())
    for i, (odom, ranges) in enumerate(zip(d.odom, d.ranges, strict=True)):
        slam.add_scan(i * 100_000_000, odom, ranges, d.angles)
    return slam, truth


def grid_of(slam: RobotSlam) -> OccupancyGrid:
    grid = OccupancyGrid(GridParams(resolution_m=0.05, padding_m=1.0))
    for kf, pose in zip(slam.keyframes, slam.keyframe_poses(), strict=True):
        grid.insert_scan(pose, kf.hits, kf.misses)
    return grid


def test_keyframes_in_the_room_next_door_do_not_refute_a_right_transform() -> None:
    walls = two_rooms()
    a, truth_a = robot_in(walls, [(1.0, 3.0), (4.2, 3.0), (4.2, 0.8)], "a")
    b, truth_b = robot_in(walls, [(9.5, 0.8), (5.8, 0.8), (5.8, 3.2)], "b")
    right = between(truth_a[0], truth_b[0])          # b's frame in a's
    share = known_share(grid_of(a))
    # without the rule: b's keyframes beside a's, a wall apart, are tried and none matches:
    # three tried and none matched refused such a merge
    tried = [0]
    assert cross_matches(a, b, T_ab=right, tried=tried) == [] and tried[0] >= 3
    # with it, they are no test of the transform
    tried = [0]
    assert cross_matches(a, b, T_ab=right, tried=tried, known=share) == [] and tried[0] == 0
    # a wrong transform that puts b's walls into a's room is still tried, and fails
    wrong = compose(np.array([-4.0, 0.0, 0.0]), right)
    tried = [0]
    assert cross_matches(a, b, T_ab=wrong, tried=tried, known=share) == [] and tried[0] >= 3
    # and a keyframe that does match is counted, whatever its near side
    tried = [0]
    same = cross_matches(a, a, T_ab=np.zeros(3), tried=tried, known=share)
    assert same and tried[0] >= len(same)
