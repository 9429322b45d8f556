"""Which of another team's keyframes can test a transform on a map: those whose points' near
side the map knows (``server.rendezvous.maps.known_share``)."""

from __future__ import annotations

import math

import numpy as np

from server.rendezvous.maps import known_share
from server.slam.grid import GridParams, OccupancyGrid


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
