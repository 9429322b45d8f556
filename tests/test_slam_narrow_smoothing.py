"""A narrow sensor's averaged pose: kept matches that no longer agree with the newest one are
dropped rather than averaged in (``NarrowSensor._smoothed``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from server.slam.config import SlamConfig
from server.slam.frontend import FrontendMatch, MatchKind
from server.slam.heading_ties import HeadingTies
from server.slam.narrow import SMOOTHED_MAX_SHIFT_M, NarrowSensor
from server.slam.smoothing import KeptMatch
from server.slam.view import SlamStats

INFO = np.diag([1e4, 1e4, 1e5])


def sensor_with(kept_x: list[float]) -> tuple[NarrowSensor, SimpleNamespace]:
    """A sensor whose kept matches put the robot at (x, 0, 0), on an anchor at the origin, at
    the same odometry pose as now (nothing to carry them by)."""
    cfg = SlamConfig()
    sensor = NarrowSensor(cfg, HeadingTies(cfg.square_walls))
    sensor.recent.matches = [KeptMatch(7, np.array([x, 0.0, 0.0]), INFO, np.zeros(3))
                             for x in kept_x]
    slam = SimpleNamespace(trajectory=SimpleNamespace(key=lambda i: 7),
                           anchor=SimpleNamespace(index=0, T_map_kf=np.zeros(3)),
                           graph=SimpleNamespace(pose=lambda key: np.zeros(3)),
                           stats=SlamStats())
    return sensor, slam


def test_matches_that_agree_are_averaged() -> None:
    sensor, slam = sensor_with([0.03, 0.04, 0.05])
    m = FrontendMatch(np.zeros(3), MatchKind.ICP, INFO, 1.0)
    got = sensor._smoothed(slam, m, np.zeros(3))   # type: ignore[arg-type]
    assert 0.02 < got.T_map_robot[0] < 0.04       # pulled towards the kept ones
    assert slam.stats.smoothing_resets == 0 and len(sensor.recent.matches) == 4


@pytest.mark.parametrize("kind", [MatchKind.ICP, MatchKind.DEGENERATE])
def test_matches_far_from_the_newest_are_dropped(kind: MatchKind) -> None:
    sensor, slam = sensor_with([1.0] * 9)          # a metre off, as in a run where it struck
    m = FrontendMatch(np.zeros(3), kind, INFO, 1.0)
    got = sensor._smoothed(slam, m, np.zeros(3))   # type: ignore[arg-type]
    assert got.T_map_robot == pytest.approx(np.zeros(3))
    assert slam.stats.smoothing_resets == 1 and len(sensor.recent.matches) == 1
    # just inside the bound, the average stands
    sensor, slam = sensor_with([SMOOTHED_MAX_SHIFT_M * 1.05] * 9)
    got = sensor._smoothed(slam, m, np.zeros(3))   # type: ignore[arg-type]
    assert 0.0 < got.T_map_robot[0] <= SMOOTHED_MAX_SHIFT_M
    assert slam.stats.smoothing_resets == 0


def test_views_taken_standing_still_keep_the_odometrys_pose() -> None:
    """While the camera turns for a whole scan and the odometry does not move, a view's match
    does not move the pose (the whole scan will place it); once the robot drives, it does."""
    from server.slam.scan import ScanPoints

    sensor, slam = sensor_with([])
    view = ScanPoints(np.array([[1.0, 0.0], [1.0, 0.2]]), np.array([[-1.0, 0.0], [-1.0, 0.0]]),
                      np.array([1.0, 1.02]), np.zeros((0, 2)), np.zeros((0, 2)), 0.3, 0.0)
    pred = np.array([2.0, 1.0, 0.5])
    off = FrontendMatch(pred + np.array([0.05, 0.0, 0.0]), MatchKind.ICP, INFO, 1.0)
    odom = np.zeros(3)
    placed = [sensor.place(slam, view, off, odom, pred, pred, np.zeros(3))   # type: ignore
              for _ in range(3)]
    assert placed[0].match.T_map_robot[0] == pytest.approx(2.05)    # the first view: matched
    for p in placed[1:]:
        assert p.match.T_map_robot == pytest.approx(pred)
        assert p.match.kind == MatchKind.ODOMETRY and not p.whole
    moved = np.array([0.2, 0.0, 0.0])                               # it drives on
    p = sensor.place(slam, view, off, moved, pred, pred, moved)      # type: ignore[arg-type]
    assert p.match.kind == MatchKind.ICP and p.match.T_map_robot[0] > 2.04


def test_a_narrow_robot_beside_a_wide_teammate_closes_no_loops_of_its_own() -> None:
    from server.slam import RobotSlam

    cam, lidar = RobotSlam("a"), RobotSlam("b")
    cam.narrow = True
    assert not cam._beside_a_wide_teammate()          # alone: its own loops are all it has
    cam.guides = [lidar]
    assert not cam._beside_a_wide_teammate()          # not in one graph yet
    lidar.graph = cam.graph
    assert cam._beside_a_wide_teammate()
    lidar.narrow = True                               # a narrow teammate drifts as it does
    assert not cam._beside_a_wide_teammate()
    cam.narrow, lidar.narrow = False, False           # a LIDAR robot closes its loops
    assert not cam._beside_a_wide_teammate()
