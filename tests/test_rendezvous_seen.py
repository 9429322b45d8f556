"""What of a keyframe's scan another robot's map saw, and from which side
(``server.rendezvous.maps.seen_fraction``): the test a merge's map check puts a short, narrow
sensor's keyframe to before it counts it as tried."""

from __future__ import annotations

import math

import numpy as np

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
