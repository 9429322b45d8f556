"""Depth pseudo-scan: four synthetic depth images of a known rectangular room."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot_agent.drivers.depth_scan import DepthScanError, DepthView, fan, pseudo_scan
from schemas.messages import ranges_from_mm

W, H = 640, 48
HFOV = math.radians(87.0)
FX = (W / 2) / math.tan(HFOV / 2)
CX = (W - 1) / 2
#: the room's walls relative to the robot: x from -1.2 to 3.5 m, y from -0.8 to 1.5 m
X_MIN, X_MAX, Y_MIN, Y_MAX = -1.2, 3.5, -0.8, 1.5


def wall_distance(theta: np.ndarray) -> np.ndarray:
    """Distance from the robot to the rectangle's wall along direction ``theta``."""
    c, s = np.cos(theta), np.sin(theta)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, X_MAX / c, np.where(c < 0, X_MIN / c, np.inf))
        ty = np.where(s > 0, Y_MAX / s, np.where(s < 0, Y_MIN / s, np.inf))
    return np.minimum(tx, ty)


def render(yaw: float, scale_m: float = 0.001) -> DepthView:
    """A depth image (uint16 millimetres, like a RealSense) of the room at heading ``yaw``."""
    alpha = np.arctan2(CX - np.arange(W), FX)
    z = wall_distance(yaw + alpha) * np.cos(alpha)
    img = np.tile(np.rint(z / scale_m), (H, 1)).astype(np.uint16)
    img[: H // 3, ::7] = 0              # holes off the middle row do not matter
    return DepthView(yaw, img, scale_m)


def test_four_views_of_a_rectangular_room_give_its_ranges() -> None:
    views = [render(math.radians(a)) for a in (0, 90, 180, 270)]
    sweep = pseudo_scan(views, FX, CX, stamp_ns=1, beams=360, max_range_m=3.0)
    r = ranges_from_mm(sweep.ranges_mm)
    theta = sweep.angle_min_rad + sweep.angle_increment_rad * np.arange(360)
    # a beam reads the nearest wall point within its width (1°)
    half = sweep.angle_increment_rad / 2
    want = wall_distance(theta[:, None] + np.linspace(-half, half, 41)[None, :]).min(axis=1)
    # beams inside a fan: within the 87° of a view
    offset = np.abs(np.remainder(theta + math.pi / 4, math.pi / 2) - math.pi / 4)
    inside = offset < math.radians(43.0)
    near = inside & (want <= 2.95)
    far = inside & (want > 3.05)
    assert near.sum() > 200 and far.sum() > 20
    # columns are 1/fx rad apart, so a beam's edge is found to within that much turn
    slope = np.abs(wall_distance(theta + 1e-4) - wall_distance(theta - 1e-4)) / 2e-4
    tolerance = 0.002 + slope / FX
    assert np.all(np.abs(r[near] - want[near]) <= tolerance[near])
    assert np.isinf(r[far]).all()                          # saturated at 3 m: no return
    # the 3° gaps between the 87° fans have no readings
    gaps = offset > math.radians(44.0)
    assert gaps.sum() >= 4 and np.isinf(r[gaps]).all()
    assert sweep.range_max_mm == 3000 and sweep.angle_min_rad == -math.pi


def test_a_single_view_is_z_over_cos_alpha_and_zeros_are_no_returns() -> None:
    z = np.full((5, 5), 2.0)
    z[2, 0] = 0.0
    angles, r = fan(DepthView(0.5, z), fx=2.0, cx=2.0)
    alpha = np.arctan2(2.0 - np.arange(5), 2.0)
    assert np.allclose(angles, 0.5 + alpha)
    assert np.isinf(r[0]) and np.allclose(r[1:], 2.0 / np.cos(alpha[1:]))
    assert angles[0] > angles[-1]      # left of the image is counter-clockwise


def test_bad_depth_input_is_a_typed_error() -> None:
    with pytest.raises(DepthScanError, match="shape"):
        fan(DepthView(0.0, np.zeros(10)), 1.0, 1.0)
    with pytest.raises(DepthScanError, match="no depth views"):
        pseudo_scan([], FX, CX, 0)
