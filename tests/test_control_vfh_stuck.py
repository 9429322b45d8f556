"""VFH avoidance in a kinematic simulation with a simulated LIDAR; stuck detection; recovery."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.control import (
    PurePursuit,
    PursuitParams,
    Recovery,
    StampOrderError,
    StuckDetector,
    Twist,
    Vfh,
    world_to_robot,
)
from tests.test_control_pursuit import DT, integrate

ROBOT_R = 0.13


def lidar_points(pose: np.ndarray, centre: np.ndarray, radius: float,
                 beams: int = 400, max_range: float = 10.0) -> np.ndarray:
    """Hits of a 360° LIDAR on one disc obstacle, in the robot frame."""
    ang = pose[2] + np.linspace(-math.pi, math.pi, beams, endpoint=False)
    d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    oc = pose[:2] - centre
    b = d @ oc
    c = oc @ oc - radius * radius
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    hit = (disc >= 0) & (t > 0) & (t < max_range)
    world = pose[:2] + t[hit, None] * d[hit]
    return world_to_robot(pose, world)


def test_no_obstacle_passes_the_command_through() -> None:
    twist = Twist(0.3, 0.1)
    res = Vfh().evaluate(twist, 0.0, np.array([[3.0, 0.0], [0.0, 2.0]]))
    assert not res.active and res.twist == twist


def test_obstacle_ahead_turns_away() -> None:
    # A 0.3 m wide box 0.45 m ahead, slightly to the left: turn right.
    ys = np.linspace(-0.1, 0.2, 10)
    pts = np.stack([np.full_like(ys, 0.45), ys], axis=1)
    vfh = Vfh()
    res = vfh.evaluate(Twist(0.3, 0.0), 0.0, pts)
    assert res.active and not res.blocked
    assert res.heading_rad < -0.2 and res.twist.omega_rps < 0
    blocked, _ = vfh.blocked_sectors(pts)
    assert not blocked[vfh._sector(res.heading_rad)]
    assert blocked[vfh._sector(0.0)]


def test_other_robot_ahead_is_avoided() -> None:
    res = Vfh().evaluate(Twist(0.3, 0.0), 0.0, np.zeros((0, 2)), others_robot_xy=[[0.5, 0.05]])
    assert res.active and abs(res.heading_rad) > 0.3


def test_surrounded_turns_on_the_spot() -> None:
    ang = np.linspace(-math.pi, math.pi, 72, endpoint=False)
    ring = 0.3 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    res = Vfh().evaluate(Twist(0.3, 0.0), 0.0, ring)
    assert res.blocked and res.twist.v_mps == 0.0 and abs(res.twist.omega_rps) > 0


@pytest.mark.parametrize("offset", [0.0, 0.08, -0.08])
def test_drives_around_an_obstacle_on_the_path(offset: float) -> None:
    """Pure pursuit along a straight path through a 0.2 m disc; VFH must keep the robot's body
    off it and the robot must still reach the goal."""
    centre, radius = np.array([2.0, offset]), 0.2
    path = np.array([[0.0, 0.0], [4.0, 0.0]])
    pp = PurePursuit(PursuitParams(goal_tolerance_m=0.2))
    vfh = Vfh()
    pose = np.array([0.0, 0.0, 0.0])
    min_gap, reached, was_active = math.inf, False, False
    for _ in range(int(60 / DT)):
        step = pp.step(pose, path)
        if step.reached:
            reached = True
            break
        res = vfh.evaluate(step.twist, step.heading_error_rad, lidar_points(pose, centre, radius))
        was_active |= res.active
        pose = integrate(pose, res.twist)
        min_gap = min(min_gap, float(np.hypot(*(pose[:2] - centre))) - radius - ROBOT_R)
    assert reached and was_active
    assert min_gap > 0.0


def test_stuck_detector() -> None:
    det = StuckDetector(window_s=5.0, min_progress_m=0.15)
    t = 0.0
    for _ in range(200):                       # 0.3 m/s for 10 s: never stuck
        assert not det.update(t, (0.3 * t, 0.0, 0.0))
        t += 0.05
    x = 0.3 * t
    stuck_at = None
    for _ in range(200):                       # then pinned against something
        if det.update(t, (x + 0.01 * math.sin(t), 0.0, 0.0)):
            stuck_at = t
            break
        t += 0.05
    # The window still held the last 0.15 m of motion until 0.5 s before its end.
    assert stuck_at is not None and 4.45 <= stuck_at - 10.0 <= 5.05
    det.reset()
    assert not det.update(t + 1, (x, 0.0, 0.0))
    with pytest.raises(StampOrderError):
        det.update(t, (x, 0.0, 0.0))


def test_back_and_forth_counts_as_stuck() -> None:
    det = StuckDetector(window_s=4.0, min_progress_m=0.15)
    flags = [det.update(0.1 * k, (0.3 * math.sin(0.1 * k * math.pi), 0.0, 0.0))
             for k in range(100)]  # oscillates ±0.3 m with a 2 s period
    assert any(flags[60:])


def test_recovery_backs_up_then_turns_to_the_open_side() -> None:
    rec = Recovery()
    # Wall close on the right, open on the left, nothing behind.
    right = np.stack([np.linspace(-1, 1, 20), np.full(20, -0.3)], axis=1)
    left = np.stack([np.linspace(-1, 1, 20), np.full(20, 3.0)], axis=1)
    rec.start(0.0, np.concatenate([right, left]))
    assert rec.active
    first = rec.command(0.1)
    assert first is not None and first.v_mps < 0 and first.omega_rps == 0
    turn = rec.command(2.5)
    assert turn is not None and turn.v_mps == 0 and turn.omega_rps > 0
    assert rec.command(10.0) is None and not rec.active


def test_recovery_skips_backing_up_when_blocked_behind() -> None:
    rec = Recovery()
    behind = np.array([[-0.25, 0.0], [-0.25, 0.1]])
    rec.start(0.0, behind)
    first = rec.command(0.1)
    assert first is not None and first.v_mps == 0 and first.omega_rps != 0
