"""``RobotSlam`` as the daemon will use it: one scan at a time from a 360° simulated LIDAR,
bad input rejected with a typed error, several robots in one graph."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from factors.scan_match import scan_match_factor
from schemas.se2 import between, compose, inverse, transform_points, wrap_angle
from server.slam import RobotSlam, SlamConfig, SlamInputError
from server.slam.backend import PoseGraph
from tests.test_slam_synthetic import align_error, cast, drive, room_world, waypoints_path

PATH = [(1.0, 1.0), (8.5, 1.0), (8.5, 4.5), (1.5, 4.5), (1.5, 2.0)]


@pytest.fixture(scope="module")
def room_drive() -> object:
    truth = waypoints_path(PATH, 0.1)
    return drive(room_world(), truth, n_beams=400, odom_drift_rad_per_m=0.02, odom_scale=1.03)


def feed(slam: RobotSlam, d: object, stop: int | None = None) -> None:
    for i, (odom, ranges) in enumerate(zip(d.odom, d.ranges, strict=True)):  # type: ignore[attr-defined]
        if stop is not None and i >= stop:
            break
        slam.add_scan(1_000_000_000 + i * 100_000_000, odom, ranges, d.angles)  # type: ignore[attr-defined]


def test_live_lidar_run_tracks_the_truth_and_maps_the_room(room_drive: object) -> None:
    slam = RobotSlam("a", SlamConfig())
    feed(slam, room_drive)
    stamps, poses = slam.scan_poses()
    truth = room_drive.truth  # type: ignore[attr-defined]
    assert len(stamps) == len(truth) and np.all(np.diff(stamps) > 0)
    assert align_error(poses, truth).max() < 0.03
    odo_err = align_error(room_drive.odom, truth).max()  # type: ignore[attr-defined]
    assert odo_err > 0.3
    # the returned live pose is the last scan pose
    np.testing.assert_allclose(slam.pose, poses[-1], atol=1e-9)
    kf = slam.keyframes
    assert 20 < len(kf) < len(truth)
    assert slam.keyframe_poses().shape == (len(kf), 3)
    assert all(k.matchable.points.shape[1] == 2 and k.hits.shape[1] == 2 for k in kf)
    grid = slam.occupancy_grid()
    nav = grid.to_nav2()
    assert (nav == -1).any() and (nav == 0).sum() + (nav < 40).sum() > 0
    # a wall point of the world is occupied in the map (map frame = first pose frame)
    T_map_world = between(truth[0], np.zeros(3))  # world → first robot pose
    wall = transform_points(T_map_world, np.array([[5.0, 0.0]]))
    ix, iy = grid.cell_of(wall)[0]
    assert grid.occupied_mask()[iy - 1:iy + 2, ix - 1:ix + 2].any()
    assert len(slam.point_cloud()) > 200


def test_bad_input_is_rejected_with_a_typed_error(room_drive: object) -> None:
    slam = RobotSlam("b", SlamConfig())
    feed(slam, room_drive, stop=5)
    r, a = room_drive.ranges[5], room_drive.angles  # type: ignore[attr-defined]
    stamp = 1_000_000_000 + 5 * 100_000_000
    with pytest.raises(SlamInputError, match="odometry"):
        slam.add_scan(stamp, [0.0, float("nan"), 0.0], r, a)
    with pytest.raises(SlamInputError, match="older"):
        slam.add_scan(stamp - 300_000_000, room_drive.odom[5], r, a)  # type: ignore[attr-defined]
    with pytest.raises(SlamInputError, match="ranges"):
        slam.add_scan(stamp, room_drive.odom[5], r[:10], a)  # type: ignore[attr-defined]
    assert slam.stats.scans == 5  # nothing was accepted from the bad calls
    # NaN/inf ranges are beams without a return, not errors
    holes = r.copy()
    holes[::3] = np.nan
    holes[1::7] = np.inf
    pose = slam.add_scan(stamp, room_drive.odom[5], holes, a)  # type: ignore[attr-defined]
    assert np.all(np.isfinite(pose)) and slam.stats.scans == 6


def test_two_robots_share_one_graph_and_can_be_joined(room_drive: object) -> None:
    graph = PoseGraph()
    a = RobotSlam("a", SlamConfig(), graph=graph)
    b = RobotSlam("b", SlamConfig(), graph=graph, T_map_start=[10.0, 0.0, 0.0])
    feed(a, room_drive, stop=60)
    feed(b, room_drive, stop=60)  # the same drive, in its own frame
    pa, pb = a.keyframe_poses(), b.keyframe_poses()
    np.testing.assert_allclose(pb[:, :2] - [10.0, 0.0], pa[:, :2], atol=2e-3)
    # join: tie b's first key to a's first key, remove b's prior, optimise jointly
    assert b.trajectory.prior is not None and b.trajectory.prior.index is not None
    tie = scan_match_factor(a.trajectory.key(0), b.trajectory.key(0), [0.0, 0.0, 0.0],
                            np.diag([1e6, 1e6, 1e6]))
    graph.add([tie], {}, remove=[b.trajectory.prior.index])
    graph.iterate(3)
    pb2 = b.keyframe_poses()
    np.testing.assert_allclose(pb2, a.keyframe_poses(), atol=1e-3)  # b now lies on a


def test_factors_reinsert_into_a_new_graph(room_drive: object) -> None:
    slam = RobotSlam("c", SlamConfig())
    feed(slam, room_drive, stop=80)
    fresh = gtsam.NonlinearFactorGraph()
    for rec in slam.trajectory.factors:
        fresh.add(rec.factor)
    init = gtsam.Values()
    for key, T in zip(slam.trajectory.all_keys(), slam.keyframe_poses(), strict=True):
        init.insert(key, gtsam.Pose2(*T))
    est = gtsam.LevenbergMarquardtOptimizer(fresh, init).optimize()
    again = np.array([[est.atPose2(k).x(), est.atPose2(k).y(), est.atPose2(k).theta()]
                      for k in slam.trajectory.all_keys()])
    np.testing.assert_allclose(again, slam.keyframe_poses(), atol=1e-3)
    assert all(gtsam.Symbol(k).chr() == ord("c") for k in slam.trajectory.all_keys())


def test_se2_invariants_on_random_poses() -> None:
    rng = np.random.default_rng(7)
    a = rng.normal(size=(100, 3)) * [5.0, 5.0, 3.0]
    b = rng.normal(size=(100, 3)) * [5.0, 5.0, 3.0]
    np.testing.assert_allclose(compose(a, between(a, b)), wrap_b(b), atol=1e-9)
    np.testing.assert_allclose(compose(a, inverse(a))[:, :2], 0.0, atol=1e-9)
    for i in range(5):  # the scalar fast path agrees with the vectorised one
        np.testing.assert_allclose(compose(a[i], b[i]), compose(a, b)[i], atol=1e-12)
    w = wrap_angle(np.array([math.pi, -math.pi, 3 * math.pi, 0.0]))
    np.testing.assert_allclose(w, [math.pi, math.pi, math.pi, 0.0])


def wrap_b(b: np.ndarray) -> np.ndarray:
    out = b.copy()
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def test_scans_without_returns_fall_back_on_odometry(room_drive: object) -> None:
    slam = RobotSlam("d", SlamConfig())
    a = room_drive.angles  # type: ignore[attr-defined]
    for i in range(3):  # a LIDAR that sees nothing yet
        pose = slam.add_scan(i * 100_000_000, room_drive.odom[i], np.full(len(a), np.nan), a)  # type: ignore[attr-defined]
        np.testing.assert_allclose(pose, between(room_drive.odom[0], room_drive.odom[i]),  # type: ignore[attr-defined]
                                   atol=1e-9)
    for i in range(3, 40):
        slam.add_scan(i * 100_000_000, room_drive.odom[i], room_drive.ranges[i], a)  # type: ignore[attr-defined]
    assert slam.stats.matches["odometry"] == 3
    assert slam.stats.matches["icp"] >= 30
    assert slam.occupancy_grid().occupied_mask().any()


def _state_at(grid: object, xy: tuple[float, float]) -> str:
    ix, iy = grid.cell_of(np.array([xy]))[0]  # type: ignore[attr-defined]
    h, w = grid.shape  # type: ignore[attr-defined]
    if not (0 <= ix < w and 0 <= iy < h) or not grid.observed[iy, ix]:  # type: ignore[attr-defined]
        return "unknown"
    if grid.free_mask()[iy, ix]:  # type: ignore[attr-defined]
        return "free"
    return "occupied" if grid.occupied_mask()[iy, ix] else "uncertain"  # type: ignore[attr-defined]


@pytest.mark.parametrize(("sensor_max", "free_until", "unknown_from"),
                         [(None, None, 3.5), (10.0, 4.6, 5.5), (3.0, 2.6, 3.5)])
def test_beams_without_return_clear_free_space_up_to_the_sensor_range(
        sensor_max: float | None, free_until: float | None, unknown_from: float) -> None:
    """A room open on one side: beams into the opening return nothing. They mark free space
    only when the sensor's range is known, and never beyond it or ``no_return_free_m``."""
    walls = [((-2.0, -2.0), (-2.0, 2.0)), ((-2.0, 2.0), (0.5, 2.0)), ((-2.0, -2.0), (0.5, -2.0))]
    angles = -math.pi + 2 * math.pi * np.arange(400) / 400
    ranges = cast(walls, np.zeros(3), angles)
    assert np.isinf(ranges).sum() > 100
    slam = RobotSlam("a", SlamConfig())
    slam.add_scan(1_000, (0.0, 0.0, 0.0), ranges, angles, sensor_max)
    grid = slam.occupancy_grid()
    assert _state_at(grid, (-1.0, 0.0)) == "free"       # toward the wall behind: hits
    if free_until is not None:
        assert _state_at(grid, (free_until, 0.0)) == "free"
    assert _state_at(grid, (unknown_from, 0.0)) == "unknown"
    assert not any(_state_at(grid, (x, 0.0)) == "occupied" for x in np.arange(0.3, 6.0, 0.1))


def test_stamped_rows_grow_search_and_pickle_as_columns() -> None:
    """Per-scan rows (stamp, tag, values) in growing columns: appended in order, read back
    as arrays, pickled as three arrays (not one object per row) and appendable after."""
    import pickle

    from server.slam.stamped import StampedRows

    rows = StampedRows(3)
    for i in range(100):
        rows.append(1000 + 10 * i, (i, 2.0 * i, -i), tag=i // 7)
    assert len(rows) == 100 and rows.stamps[-1] == 1990 and rows.tags[50] == 7
    assert np.array_equal(rows.values[3], [3.0, 6.0, -3.0])
    back = pickle.loads(pickle.dumps(rows))
    assert np.array_equal(back.stamps, rows.stamps) and np.array_equal(back.values, rows.values)
    back.append(5000, (1.0, 1.0, 1.0), tag=99)
    assert len(back) == 101 and back.row(100)[:2] == (5000, 99) and len(rows) == 100
    assert len(pickle.dumps(rows)) < 100 * 45      # 40 bytes of data a row, no objects
