"""What of a keyframe's scan another robot's map saw, and from which side
(``server.rendezvous.maps.seen_fraction``): the test a merge's map check puts a short, narrow
sensor's keyframe to before it counts it as tried."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.rendezvous.maps import seen_fraction
from server.slam.icp import PointMap


def wall(x: float, facing: float) -> tuple[np.ndarray, np.ndarray]:
    """A wall along y at ``x`` from y −2 to 2 m, its normals pointing along ``facing`` (±1 in x)."""
    y = np.linspace(-2.0, 2.0, 41)
    pts = np.column_stack([np.full_like(y, x), y])
    return pts, np.tile([facing, 0.0], (len(y), 1))


def test_a_wall_seen_from_its_other_side_is_not_seen() -> None:
    # robot a mapped the wall at x = 0 from the west: its normals point west (−x)
    target = PointMap(*wall(0.0, -1.0))
    # robot b's scan, in its own frame: the wall 2 m ahead (+x), normals back at b
    pts, nrm = wall(2.0, -1.0)
    # b stands 2 m west of the wall, on a's side: all of it seen, from the same side
    assert seen_fraction(pts, nrm, target, np.array([-2.0, 0.0, 0.0]), 0.5, 0.6) == 1.0
    # b stands east of it, looking west: the same wall's other face, which a never saw
    east = np.array([2.0, 0.0, math.pi])
    assert seen_fraction(pts, nrm, target, east, 0.5, 0.6) == 0.0
    # a's map placed 0.3 m off still counts (the fit need not be perfect) ...
    assert seen_fraction(pts, nrm, target, np.array([-2.3, 0.0, 0.0]), 0.5, 0.6) == 1.0
    # ... a wall a never mapped does not; half of it: half
    assert seen_fraction(pts, nrm, target, np.array([-2.0, 10.0, 0.0]), 0.5, 0.6) == 0.0
    half = seen_fraction(pts, nrm, target, np.array([-2.0, 2.0, 0.0]), 0.5, 0.6)
    assert 0.4 < half < 0.7
    assert seen_fraction(pts[:0], nrm[:0], target, np.zeros(3), 0.5, 0.6) == 0.0


class Walls:
    """Keyframes that saw walls with these normals' angles [rad], at these headings: all
    ``wall_grid`` reads of a robot's SLAM."""

    def __init__(self, normals_rad: np.ndarray, headings_rad: list[float]) -> None:
        class Kf:
            matchable = type("M", (), {"normals": np.column_stack(
                [np.cos(normals_rad), np.sin(normals_rad)])})()
        self.keyframes = [Kf() for _ in headings_rad]
        self._poses = np.array([[0.0, 0.0, h] for h in headings_rad])

    def keyframe_poses(self) -> np.ndarray:
        return self._poses


def test_far_sightings_turn_is_checked_on_the_two_maps_square_walls() -> None:
    from server.rendezvous.maps import square_walls_agree, wall_grid

    rng = np.random.default_rng(0)
    square = rng.integers(0, 4, 200) * (math.pi / 2) + rng.normal(0, 0.01, 200)
    a = Walls(square + math.radians(0.5), [0.0, math.pi / 2])      # a's walls at 0.5°
    b = Walls(square, [0.3, 0.3 + math.pi])                         # b's own frame: 17.2°
    phi, strength = wall_grid([a])                                  # type: ignore[list-item]
    assert math.degrees(phi) == pytest.approx(0.5, abs=0.1) and strength > 0.95
    # the sightings turn b onto a: right within 1.5° (mod 90°), wrong by 4° not
    for turn_deg, ok in ((-16.7, True), (-16.7 + 90.0, True), (-16.7 + 1.0, True),
                         (-16.7 + 4.0, False), (-16.7 - 2.0, False)):
        got = square_walls_agree([a], [b], math.radians(turn_deg), 1.5, 0.5)  # type: ignore[list-item]
        assert got is ok, turn_deg
    # walls on no square grid (a round building) confirm nothing
    round_ = Walls(rng.uniform(-math.pi, math.pi, 400), [0.0])
    assert not square_walls_agree([a], [round_], 0.0, 1.5, 0.5)   # type: ignore[list-item]
