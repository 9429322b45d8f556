"""Pure pursuit in a kinematic (unicycle) simulation: straight, curved and hairpin paths."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.se2 import wrap_angle
from server.control import PurePursuit, PursuitParams, Twist, closest_point

DT = 0.05
PARAMS = PursuitParams(lookahead_m=1.0, v_mps=0.3, omega_max_rps=1.5, goal_tolerance_m=0.2)


def integrate(pose: np.ndarray, twist: Twist, dt: float = DT) -> np.ndarray:
    x, y, th = pose
    th2 = th + twist.omega_rps * dt
    mid = th + 0.5 * twist.omega_rps * dt
    return np.array([x + twist.v_mps * math.cos(mid) * dt, y + twist.v_mps * math.sin(mid) * dt,
                     wrap_angle(th2)])


def drive(path: np.ndarray, pose: tuple[float, float, float], max_s: float = 120.0
          ) -> tuple[np.ndarray, list[Twist], bool]:
    pp = PurePursuit(PARAMS)
    p = np.array(pose, dtype=np.float64)
    poses, twists = [p], []
    for _ in range(int(max_s / DT)):
        step = pp.step(p, path)
        if step.reached:
            return np.array(poses), twists, True
        twists.append(step.twist)
        p = integrate(p, step.twist)
        poses.append(p)
    return np.array(poses), twists, False


def cross_track(path: np.ndarray, xy: np.ndarray) -> float:
    return closest_point(path, xy)[2]


def check_limits(twists: list[Twist]) -> None:
    assert all(abs(t.omega_rps) <= PARAMS.omega_max_rps + 1e-12 for t in twists)
    assert all(0.0 <= t.v_mps <= PARAMS.v_mps + 1e-12 for t in twists)


def test_converges_onto_a_straight_path() -> None:
    path = np.stack([np.linspace(0, 12, 25), np.zeros(25)], axis=1)
    poses, twists, reached = drive(path, (0.0, 1.0, math.pi / 4))
    assert reached
    check_limits(twists)
    after = poses[poses[:, 0] > 5.0]
    assert len(after) > 0
    assert max(cross_track(path, p[:2]) for p in after) < 0.03
    assert np.hypot(*(poses[-1, :2] - path[-1])) < PARAMS.goal_tolerance_m


def test_converges_onto_a_circular_arc() -> None:
    R = 2.0
    phi = np.linspace(-math.pi / 2, math.pi, 200)
    path = np.stack([R * np.cos(phi), R * np.sin(phi)], axis=1)  # counter-clockwise
    # Start 0.3 m outside the arc, heading along its tangent.
    poses, twists, reached = drive(path, (0.0, -R - 0.3, 0.0))
    assert reached
    check_limits(twists)
    travelled = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    settled = poses[(travelled > 2.5) & (travelled < travelled[-1] - 1.0)]
    assert len(settled) > 50
    # On a circle pure pursuit's arc is the circle itself: the error settles near zero.
    assert max(cross_track(path, p[:2]) for p in settled) < 0.05


def test_turns_in_place_when_the_path_is_behind() -> None:
    path = np.array([[0.0, 0.0], [-5.0, 0.0]])
    step = PurePursuit(PARAMS).step((0.0, 0.0, 0.1), path)
    assert step.twist.v_mps == 0.0 and step.twist.omega_rps > 0.0  # shorter way is to the left
    assert abs(step.heading_error_rad) > math.pi / 2
    poses, _, reached = drive(path, (0.0, 0.0, 0.1))
    assert reached and max(abs(p[1]) for p in poses) < 0.06


def test_reached_and_stop_at_goal() -> None:
    pp = PurePursuit(PARAMS)
    path = np.array([[0.0, 0.0], [1.0, 0.0]])
    step = pp.step((0.9, 0.05, 0.0), path)
    assert step.reached and step.twist == Twist(0.0, 0.0)
    assert pp.reached((0.9, 0.05, 0.0), path) and not pp.reached((0.5, 0.0, 0.0), path)


def test_hairpin_is_followed_not_cut() -> None:
    out = np.stack([np.linspace(0, 5, 51), np.zeros(51)], axis=1)
    back = np.stack([np.linspace(5, 0, 51), np.full(51, 0.6)], axis=1)
    path = np.concatenate([out, back])
    poses, _, reached = drive(path, (0.0, 0.0, 0.0))
    assert reached
    assert poses[:, 0].max() > 4.5  # went round the far end instead of jumping across


def test_long_segments_of_a_planned_path_are_followed_past_their_corners() -> None:
    """A planner's path has few points (segments of several metres). The progress moves on
    past each corner: the robot reaches the end, never circling a look-ahead point held a
    look-ahead past the first corner (it once did, until an errand was given up)."""
    path = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 4.0], [9.0, 4.0]])
    poses, twists, reached = drive(path, (0.0, 0.0, 0.0), max_s=80.0)
    assert reached
    check_limits(twists)
    length = 13.0
    assert len(twists) * DT < 1.3 * length / PARAMS.v_mps
    # no turning on the spot once under way (the corners are taken on arcs)
    assert sum(1 for t in twists if t.v_mps == 0.0) * DT < 1.0
    assert max(cross_track(path, p[:2]) for p in poses) < 0.6


def test_saturated_turn_keeps_curvature() -> None:
    pp = PurePursuit(PursuitParams(lookahead_m=0.3, v_mps=1.0, omega_max_rps=0.5,
                                   goal_tolerance_m=0.05))
    step = pp.step((0.0, 0.0, 0.0), np.array([[0.0, 0.0], [0.2, 0.15], [0.4, 0.3]]))
    assert step.twist.omega_rps == pytest.approx(0.5)
    assert step.twist.v_mps < 1.0
    lx, ly = step.lookahead_xy
    kappa = 2 * ly / (lx * lx + ly * ly)
    assert step.twist.omega_rps / step.twist.v_mps == pytest.approx(kappa)


def test_bad_path_is_rejected() -> None:
    with pytest.raises(ValueError):
        PurePursuit().step((0.0, 0.0, 0.0), np.array([[0.0, np.nan]]))
    with pytest.raises(ValueError):
        PurePursuit().step((0.0, 0.0, 0.0), np.zeros((0, 2)))
