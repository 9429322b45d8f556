"""Loop closure: a drifting loop is closed and its drift removed; wrong closures are rejected
before they enter the graph, or taken out again when they disagree with it."""

from __future__ import annotations

import math

import numpy as np

from schemas.se2 import between, compose
from server.slam import RobotSlam, SlamConfig
from server.slam.config import LoopClosureConfig
from server.slam.icp import IcpParams
from server.slam.keyframes import Keyframe
from server.slam.loop_closure import LoopCloser, LoopClosure
from server.slam.scan import scan_to_points
from tests.test_slam_synthetic import (
    align_error,
    box,
    cast,
    drive,
    ring_world,
    room_world,
    waypoints_path,
)

LOOP_PATH = [(1.0, 1.0), (13.0, 1.0), (13.0, 9.0), (1.0, 9.0), (1.0, 1.0), (6.0, 1.0)]


def run_drive(cfg: SlamConfig, d: object) -> RobotSlam:
    slam = RobotSlam("a", cfg)
    for i, (odom, ranges) in enumerate(zip(d.odom, d.ranges, strict=True)):  # type: ignore[attr-defined]
        slam.add_scan(i * 100_000_000, odom, ranges, d.angles)  # type: ignore[attr-defined]
    return slam


def test_synthetic_loop_is_closed_and_drift_removed() -> None:
    truth = waypoints_path(LOOP_PATH, 0.2)
    d = drive(ring_world(), truth, n_beams=180, fov_rad=math.pi, odom_drift_rad_per_m=0.006,
              odom_scale=1.02)
    # front-end off: the poses drift like the odometry until a loop closure corrects them
    open_loop = run_drive(SlamConfig.model_validate(
        {"matcher": {"enabled": False}, "loop": {"enabled": False}}), d)
    closed = run_drive(SlamConfig.model_validate({"matcher": {"enabled": False}}), d)
    end_open = align_error(open_loop.scan_poses()[1], truth)[-1]
    end_closed = align_error(closed.scan_poses()[1], truth)[-1]
    assert end_open > 0.8  # the odometry drifted by about a metre around the loop
    assert closed.stats.loop_closures >= 1
    assert end_closed < 0.25 * end_open
    assert closed.stats.loop_closures_removed == 0


def chain(closer: LoopCloser, poses: np.ndarray) -> None:
    for i in range(1, len(poses)):
        closer.add_edge(i - 1, i, float(np.hypot(*(poses[i, :2] - poses[i - 1, :2]))))


def keyframes_from(walls: list, poses: np.ndarray, start_index: int = 0) -> list[Keyframe]:
    angles = -math.pi / 2 + math.pi * np.arange(181) / 180
    out = []
    for i, T in enumerate(poses):
        sc = scan_to_points(cast(walls, T, angles), angles, 0.05, 30.0)
        out.append(Keyframe.create(start_index + i, i, sc, T))
    return out


def test_wrong_candidate_is_rejected_by_verification() -> None:
    # submap: keyframes in one room; query: keyframes in a different room, placed on top of it
    room_a = room_world()
    room_b = box(0.0, 0.0, 4.0, 12.0) + box(1.5, 5.0, 2.5, 5.5)
    poses_a = np.array([[1.5 + 0.3 * i, 2.0, 0.1 * i] for i in range(6)])
    poses_b = np.array([[1.8 + 0.05 * i, 2.0 + 0.3 * i, 1.2] for i in range(6)])
    kfs = keyframes_from(room_a, poses_a) + keyframes_from(room_b, poses_b, 6)
    poses = np.concatenate([poses_a, poses_b])
    cfg = LoopClosureConfig(block_keyframes=6, min_graph_distance_m=0.0, query_keyframes=3)
    closer = LoopCloser(cfg, IcpParams())
    chain(closer, poses)
    closer.maybe_close_submap(kfs[:6], poses[:6])
    assert closer.search(11, kfs, poses) == []
    assert closer.stats.candidates >= 1
    assert closer.stats.accepted == 0
    rejected = closer.stats.rejected_score + closer.stats.rejected_icp
    assert rejected + closer.stats.rejected_degenerate >= 1


def test_same_place_is_accepted_by_verification() -> None:
    room = room_world()
    poses_a = np.array([[1.5 + 0.3 * i, 2.0, 0.1 * i] for i in range(6)])
    drift = np.array([0.3, -0.2, math.radians(4.0)])  # the estimate of the revisit is off
    poses_b_true = np.array([[2.0 + 0.2 * i, 2.3, 0.2] for i in range(6)])
    kfs = keyframes_from(room, poses_a) + keyframes_from(room, poses_b_true, 6)
    poses = np.concatenate([poses_a, compose(np.broadcast_to(drift, (6, 3)), poses_b_true)])
    cfg = LoopClosureConfig(block_keyframes=6, min_graph_distance_m=0.0, query_keyframes=3,
                            confirm_correction_m=1.0)
    closer = LoopCloser(cfg, IcpParams())
    chain(closer, poses)
    closer.maybe_close_submap(kfs[:6], poses[:6])
    found = closer.search(11, kfs, poses)
    assert len(found) == 1
    lc = found[0]
    truth = between(poses_a[lc.anchor], poses_b_true[lc.keyframe - 6])
    assert np.hypot(*(lc.T_anchor_kf[:2] - truth[:2])) < 0.02
    assert abs(lc.T_anchor_kf[2] - truth[2]) < math.radians(0.5)


def revisit_after_drift(min_score: float = 0.7) -> tuple[LoopCloser, list[Keyframe], np.ndarray]:
    """A room seen from six keyframes, then again after the odometry drifted 0.9 m / 6°; the
    first six form a submap."""
    room = room_world()
    poses_a = np.array([[1.5 + 0.3 * i, 2.0, 0.1 * i] for i in range(6)])
    drift = np.array([0.8, -0.4, math.radians(6.0)])
    poses_b_true = np.array([[2.0 + 0.2 * i, 2.3, 0.2] for i in range(12)])
    kfs = keyframes_from(room, poses_a) + keyframes_from(room, poses_b_true, 6)
    poses = np.concatenate([poses_a, compose(np.broadcast_to(drift, (12, 3)), poses_b_true)])
    cfg = LoopClosureConfig(block_keyframes=6, min_graph_distance_m=0.0, query_keyframes=3,
                            radius_base_m=1.5, confirm_correction_m=0.5,
                            confirm_min_score=min_score)
    closer = LoopCloser(cfg, IcpParams())
    chain(closer, poses)
    closer.maybe_close_submap(kfs[:6], poses[:6])
    return closer, kfs, poses


def test_large_correction_waits_for_confirmation() -> None:
    closer, kfs, poses = revisit_after_drift()
    assert closer.search(10, kfs[:11], poses[:11]) == []  # one sighting: pending
    assert closer.stats.pending == 1
    confirmed = closer.search(17, kfs, poses)  # a later, independent one agrees
    assert len(confirmed) == 2


def test_a_large_correction_needs_a_strong_match() -> None:
    """A place that repeats itself (a row of like rooms) matches an old submap a few metres
    off at a middling score, and keeps doing so as the robot goes on: a large correction
    must score well before it may wait for confirmation at all."""
    for min_score, weak in ((0.7, 0), (0.999, 2)):
        closer, kfs, poses = revisit_after_drift(min_score)
        closer.search(10, kfs[:11], poses[:11])
        confirmed = closer.search(17, kfs, poses)
        assert closer.stats.rejected_weak == weak
        assert len(confirmed) == (2 if weak == 0 else 0)


def test_wrong_loop_factor_is_removed_and_does_not_bend_the_map() -> None:
    truth = waypoints_path([(1.0, 1.0), (9.0, 1.0), (9.0, 4.5)], 0.15)
    d = drive(room_world(), truth, n_beams=360, odom_drift_rad_per_m=0.0, odom_scale=1.0)
    slam = run_drive(SlamConfig.model_validate({"loop": {"enabled": False}}), d)
    before = slam.keyframe_poses()
    k = len(slam.keyframes) - 1
    # a confident but wrong closure: keyframe k claimed to be 1.5 m from where it is
    wrong = between(before[0], before[k]) + np.array([1.5, -1.0, 0.3])
    kept = slam.apply_loop_closures([LoopClosure(0, k, wrong, np.diag([1e4, 1e4, 1e4]), 0.9,
                                                 1.8)])
    after = slam.keyframe_poses()
    assert kept == 0
    assert slam.stats.loop_closures_removed == 1
    assert np.abs(after[:, :2] - before[:, :2]).max() < 0.02
    assert not [r for r in slam.trajectory.factors if r.kind == "loop"]


def test_a_narrow_sensors_keyframe_searches_a_small_window_only() -> None:
    """Far along the path, a LIDAR's keyframe searches up to ``radius_max_m``; a depth
    camera's, which shows a few metres of wall, no more than ``narrow_radius_max_m``."""
    out_and_back = [0.15 * min(i, 39 - i) for i in range(40)]   # back where it began
    poses = np.array([[1.0 + x, 2.0, 0.0] for x in out_and_back])
    kfs = keyframes_from(room_world(), poses)
    cfg = LoopClosureConfig(block_keyframes=6, min_graph_distance_m=2.0, radius_base_m=0.5,
                            radius_per_m=0.5)
    closer = LoopCloser(cfg, IcpParams())
    chain(closer, poses)
    closer.maybe_close_submap(kfs[:6], poses[:6])
    wide = closer.candidates(39, poses)
    narrow = closer.candidates(39, poses, narrow=True)
    assert wide and narrow
    assert max(r for _, r, _ in wide) > cfg.narrow_radius_max_m
    assert all(r <= cfg.narrow_radius_max_m for _, r, _ in narrow)
    assert all(a <= math.radians(cfg.narrow_angle_max_deg) + 1e-12 for _, _, a in narrow)
