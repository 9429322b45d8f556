"""A turning camera's whole scan placed on its LIDAR teammate's map (``server.slam.narrow``):
where the teammate drew the place, the whole scan is matched against the local map that holds
the teammate's walls, and corrects the drift the robot's own whole scans would carry on; a
match that would move the pose too far is refused. A synthetic room, no mission."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from server.slam.config import SlamConfig
from server.slam.heading_ties import HeadingTies
from server.slam.icp import PointMap
from server.slam.keyframes import Keyframe, gather
from server.slam.narrow import GUIDED_MAX_SHIFT_M, NarrowSensor
from server.slam.scan import scan_to_points
from server.slam.view import SlamStats

#: a room of 8 × 5 m with a pillar, corners at (-3, -2) and (5, 3)
WALLS = [((-3.0, -2.0), (5.0, -2.0)), ((5.0, -2.0), (5.0, 3.0)), ((5.0, 3.0), (-3.0, 3.0)),
         ((-3.0, 3.0), (-3.0, -2.0)), ((1.5, 0.8), (2.1, 0.8)), ((2.1, 0.8), (2.1, 1.4)),
         ((2.1, 1.4), (1.5, 1.4)), ((1.5, 1.4), (1.5, 0.8))]


def scan_from(pose: tuple[float, float, float], n: int = 720) -> tuple[np.ndarray, np.ndarray]:
    """A 360° scan of the room from ``pose`` (ray cast against its walls)."""
    x, y, th = pose
    angles = np.linspace(-math.pi, math.pi, n, endpoint=False)
    ranges = np.full(n, np.inf)
    for i, a in enumerate(angles):
        dx, dy = math.cos(th + a), math.sin(th + a)
        for (x0, y0), (x1, y1) in WALLS:
            ex, ey = x1 - x0, y1 - y0
            den = dx * ey - dy * ex
            if abs(den) < 1e-12:
                continue
            t = ((x0 - x) * ey - (y0 - y) * ex) / den
            u = ((x0 - x) * dy - (y0 - y) * dx) / den
            if t > 0 and 0 <= u <= 1:
                ranges[i] = min(ranges[i], t)
    return ranges, angles


def setup(truth: tuple[float, float, float]) -> tuple[NarrowSensor, SimpleNamespace, object]:
    cfg = SlamConfig()
    graph = object()
    ranges, angles = scan_from((0.0, 0.0, 0.0))
    kf = Keyframe.create(0, 0, scan_to_points(ranges, angles, 0.05, 10.0), np.zeros(3), False)
    poses = np.zeros((1, 3))
    mate = SimpleNamespace(graph=graph, keyframes=[kf], narrow=False,
                           keyframe_poses=lambda: poses)
    pts, nrm = gather([kf], poses)
    slam = SimpleNamespace(guides=[mate], graph=graph, local_map=PointMap(pts, nrm),
                           stats=SlamStats())
    whole_r, whole_a = scan_from(truth)
    whole = scan_to_points(whole_r, whole_a, 0.05, 3.0, normal_window=4)
    return NarrowSensor(cfg, HeadingTies(cfg.square_walls)), slam, whole


def test_a_whole_scan_is_placed_on_the_teammates_map() -> None:
    truth = (1.0, -0.5, 0.3)
    sensor, slam, whole = setup(truth)
    drifted = np.array([truth[0] + 0.15, truth[1] - 0.05, truth[2] + 0.01])
    m = sensor._match_guided(slam, whole, drifted, drifted)   # type: ignore[arg-type]
    assert m is not None
    assert m.T_map_robot[:2] == pytest.approx(truth[:2], abs=0.02)
    assert slam.stats.guided_sweeps == 1 and slam.stats.sweep_shift_m > 0.1


def test_a_match_too_far_from_the_prediction_or_without_a_teammate_is_refused() -> None:
    truth = (1.0, -0.5, 0.3)
    sensor, slam, whole = setup(truth)
    far = np.array([truth[0] + GUIDED_MAX_SHIFT_M + 0.1, truth[1], truth[2]])
    assert sensor._match_guided(slam, whole, far, far) is None   # type: ignore[arg-type]
    slam.guides = []
    near = np.array([truth[0] + 0.1, truth[1], truth[2]])
    assert sensor._match_guided(slam, whole, near, near) is None   # type: ignore[arg-type]
    assert slam.stats.guided_sweeps == 0


def test_a_match_weak_along_one_direction_keeps_the_prediction_along_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the match's information along its weakest direction is under
    ``GUIDED_WEAK_RATIO`` of the other's, it corrects the pose across that direction only
    and its σ along it over ``GUIDED_WEAK_SIGMA_M`` (the room's match, noise-free, is a full
    one: the limits are moved so that its weakest direction counts as weak)."""
    import server.slam.narrow as narrow
    from server.slam.frontend import match_scan
    from server.slam.icp import translation_degeneracy

    truth = (1.0, -0.5, 0.3)
    sensor, slam, whole = setup(truth)
    drifted = np.array([truth[0] + 0.15, truth[1] - 0.05, truth[2] + 0.01])
    full = match_scan(whole, slam.local_map, drifted, drifted, np.zeros(3), False,
                      sensor.cfg.matcher, sensor.icp_wide, None)
    v = translation_degeneracy(full.information, 1.01)
    assert v is not None
    monkeypatch.setattr(narrow, "GUIDED_WEAK_RATIO", 1.01)
    monkeypatch.setattr(narrow, "GUIDED_WEAK_SIGMA_M", 1e-6)
    m = sensor._match_guided(slam, whole, drifted, drifted)   # type: ignore[arg-type]
    assert m is not None
    across = np.array([-v[1], v[0]])
    # along the weak direction, where the prediction was; across it, where the robot is
    assert float(v @ (m.T_map_robot[:2] - drifted[:2])) == pytest.approx(0.0, abs=1e-9)
    assert float(across @ (m.T_map_robot[:2] - np.array(truth[:2]))) == \
        pytest.approx(0.0, abs=0.02)
    assert abs(float(across @ (drifted[:2] - np.array(truth[:2])))) > 0.03   # it did move
