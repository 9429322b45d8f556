"""Scan matching on synthetic scans with known answers: ICP, degeneracy, correlative search."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.se2 import compose, rotate_vectors, transform_points
from server.slam.config import MatcherConfig
from server.slam.correlative import LikelihoodField, search
from server.slam.frontend import MatchKind, icp_params, match_scan, odometry_prior
from server.slam.icp import IcpParams, PointMap, icp, translation_degeneracy
from server.slam.scan import scan_to_points
from tests.test_slam_synthetic import box, cast, room_world

ANGLES = -math.pi + 2 * math.pi * np.arange(360) / 360


def scan_at(walls: list, T: np.ndarray, noise: float = 0.0, seed: int = 0) -> object:
    r = cast(walls, T, ANGLES)
    r = r + np.random.default_rng(seed).normal(0.0, noise, len(r))
    return scan_to_points(r, ANGLES, 0.05, 30.0, min_spacing_m=0.03)


def map_at(walls: list, T: np.ndarray, noise: float = 0.0) -> PointMap:
    s = scan_at(walls, T, noise, seed=1).with_normals()
    return PointMap(transform_points(T, s.points), rotate_vectors(float(T[2]), s.normals))


@pytest.mark.parametrize("offset", [(0.15, -0.1, 0.08), (-0.2, 0.05, -0.1), (0.0, 0.0, 0.0)])
def test_icp_recovers_known_transform(offset: tuple[float, float, float]) -> None:
    walls = room_world()
    T_ref = np.array([2.0, 3.0, 0.3])
    T_true = np.array([2.6, 3.4, 0.45])
    target = map_at(walls, T_ref, noise=0.005)
    scan = scan_at(walls, T_true, noise=0.005)
    res = icp(scan.points, scan.normals, target, T_true + np.array(offset), IcpParams())
    assert res.converged
    assert np.hypot(*(res.T_map_scan[:2] - T_true[:2])) < 0.01
    assert abs(res.T_map_scan[2] - T_true[2]) < math.radians(0.3)
    assert res.inlier_fraction > 0.8
    assert not res.degenerate


def test_corridor_is_degenerate_along_its_axis() -> None:
    walls = [((-50.0, -1.0), (50.0, -1.0)), ((-50.0, 1.0), (50.0, 1.0))]
    T = np.array([0.0, 0.0, 0.0])
    target = map_at(walls, T)
    scan = scan_at(walls, np.array([0.3, 0.0, 0.0]))
    res = icp(scan.points, scan.normals, target, np.array([0.3, 0.05, 0.0]), IcpParams())
    assert res.degenerate_dir is not None
    assert abs(res.degenerate_dir[0]) > 0.99  # the weak direction is the corridor axis
    assert abs(res.T_map_scan[1]) < 0.01  # across the corridor it is still exact


def test_frontend_keeps_odometry_along_a_corridor() -> None:
    walls = [((-50.0, -1.0), (50.0, -1.0)), ((-50.0, 1.0), (50.0, 1.0))]
    target = map_at(walls, np.zeros(3))
    scan = scan_at(walls, np.array([0.3, 0.0, 0.0]))
    cfg = MatcherConfig()
    T_pred = np.array([0.32, 0.04, 0.01])
    step = np.array([0.32, 0.0, 0.0])
    m = match_scan(scan, target, T_pred, np.zeros(3), step, False, cfg, icp_params(cfg),
                   odometry_prior(step, cfg))
    assert m.kind in (MatchKind.ICP, MatchKind.DEGENERATE)
    assert abs(m.T_map_robot[0] - 0.32) < 0.02  # along: the prediction
    assert abs(m.T_map_robot[1]) < 0.01  # across: the walls
    assert abs(m.T_map_robot[2]) < math.radians(0.3)


def test_correlative_search_finds_a_large_offset() -> None:
    walls = room_world()
    T_ref = np.array([3.0, 3.0, 0.0])
    target = map_at(walls, T_ref)
    field = LikelihoodField(target.points, 0.05, sigma_m=0.05, margin_m=0.2, levels=6)
    T_true = np.array([4.0, 2.5, math.radians(25.0)])
    scan = scan_at(walls, T_true)
    guess = T_true + np.array([-0.9, 0.6, math.radians(-20.0)])
    found = search(field, scan.points, guess, 1.2, math.radians(30.0), min_score=0.5)
    assert found is not None
    assert np.hypot(*(found.T_map_scan[:2] - T_true[:2])) < 0.08
    assert abs(found.T_map_scan[2] - T_true[2]) < math.radians(1.0)
    # and ICP finishes the job from there
    res = icp(scan.points, scan.normals, target, found.T_map_scan, IcpParams())
    assert np.hypot(*(res.T_map_scan[:2] - T_true[:2])) < 0.01


def test_frontend_recovers_from_an_odometry_jump() -> None:
    walls = room_world()
    target = map_at(walls, np.array([3.0, 3.0, 0.0]))
    T_true = np.array([3.2, 3.0, math.radians(12.0)])
    scan = scan_at(walls, T_true)
    cfg = MatcherConfig()
    # odometry claims a 70° turn that did not happen
    T_last = np.array([3.1, 3.0, math.radians(5.0)])
    step = np.array([0.1, 0.0, math.radians(70.0)])
    m = match_scan(scan, target, compose(T_last, step), T_last, np.array([0.1, 0.0, 0.1]),
                   True, cfg, icp_params(cfg))
    assert m.kind != MatchKind.ODOMETRY
    assert np.hypot(*(m.T_map_robot[:2] - T_true[:2])) < 0.02
    assert abs(m.T_map_robot[2] - T_true[2]) < math.radians(0.5)


def test_translation_degeneracy_on_information() -> None:
    assert translation_degeneracy(np.diag([100.0, 100.0, 10.0]), 0.02) is None
    v = translation_degeneracy(np.diag([100.0, 0.1, 10.0]), 0.02)
    assert v is not None and abs(v[1]) > 0.99


def test_no_points_falls_back_on_odometry() -> None:
    walls = box(0.0, 0.0, 5.0, 5.0)
    target = map_at(walls, np.array([2.5, 2.5, 0.0]))
    empty = scan_to_points(np.full(360, np.inf), ANGLES, 0.05, 30.0)
    cfg = MatcherConfig()
    T_pred = np.array([2.6, 2.5, 0.0])
    m = match_scan(empty, target, T_pred, T_pred, np.zeros(3), False, cfg, icp_params(cfg))
    assert m.kind == MatchKind.ODOMETRY
    np.testing.assert_allclose(m.T_map_robot, T_pred)


def test_correlative_search_reports_ambiguity() -> None:
    # a corridor with identical niches every 2 m: shifted by one period it fits as well
    walls = [((-20.0, -1.0), (20.0, -1.0)), ((-20.0, 1.0), (20.0, 1.0))]
    for x in np.arange(-20.0, 20.0, 2.0):
        walls += box(float(x), 1.0, float(x) + 0.4, 1.3)
    target = map_at(walls, np.zeros(3))
    field = LikelihoodField(target.points, 0.1, sigma_m=0.1, margin_m=0.4, levels=6)
    scan = scan_at(walls, np.array([0.3, 0.0, 0.0]))
    found = search(field, scan.points, np.array([0.3, 0.0, 0.0]), 2.5, math.radians(10.0),
                   min_score=0.4, ambiguity_ratio=0.9)
    assert found is not None and found.second_score >= 0.9 * found.score
    # a room with a pillar and an alcove has one answer
    room = room_world()
    target = map_at(room, np.array([3.0, 3.0, 0.0]))
    field = LikelihoodField(target.points, 0.1, sigma_m=0.1, margin_m=0.4, levels=6)
    scan = scan_at(room, np.array([3.5, 2.8, 0.2]))
    found = search(field, scan.points, np.array([3.2, 3.1, 0.1]), 1.5, math.radians(20.0),
                   min_score=0.4, ambiguity_ratio=0.9)
    assert found is not None and found.second_score == 0.0
    assert np.hypot(*(found.T_map_scan[:2] - [3.5, 2.8])) < 0.15  # within a cell or so


@pytest.mark.parametrize("seed", range(30))
def test_the_compiled_loop_agrees_with_the_numpy_one(seed: int) -> None:
    """The compiled ICP (``server.slam.icp_kernel``) against the numpy loop it replaced
    (``tests/reference_icp.py``): the same pose to rounding, the same iterations and
    convergence, the same information, with and without a prior, in rooms and corridors."""
    from tests.reference_numpy import reference_icp

    rng = np.random.default_rng(seed)
    walls = room_world()
    T_ref = np.array([2.0, 3.0, 0.3])
    T_true = T_ref + np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6),
                               rng.uniform(-0.3, 0.3)])
    target = map_at(walls, T_ref, noise=0.01)
    scan = scan_at(walls, T_true, noise=0.01, seed=seed)
    guess = T_true + np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2),
                               rng.uniform(-0.1, 0.1)])
    prior = np.diag([rng.uniform(0, 400), rng.uniform(0, 400), rng.uniform(0, 4000)]) \
        if seed % 2 else None
    normals = scan.normals if seed % 3 else None
    got = icp(scan.points, normals, target, guess, IcpParams(), prior)
    want = reference_icp(scan.points, normals, target, guess, IcpParams(), prior)
    assert got.iterations == want.iterations and got.converged == want.converged
    assert np.allclose(got.T_map_scan, want.T_map_scan, rtol=0, atol=1e-9)
    assert np.allclose(got.information, want.information, rtol=1e-7, atol=1e-6)
    assert got.inlier_fraction == want.inlier_fraction
    assert got.rms_m == pytest.approx(want.rms_m, rel=1e-9)
    assert (got.degenerate_dir is None) == (want.degenerate_dir is None)


@pytest.mark.parametrize("seed", range(20))
def test_the_compiled_normals_are_the_numpy_ones_bit_for_bit(seed: int) -> None:
    """A scan's normals (``server.slam.scan.line_normals``, compiled) against the vectorised
    numpy fit it replaced: every normal equal to the last bit, NaN where it gave NaN."""
    from server.slam.scan import line_normals
    from tests.reference_numpy import reference_line_normals

    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 400))
    a = np.sort(rng.uniform(-math.pi, math.pi, n))
    r = rng.uniform(0.2, 8.0, n) if seed % 2 else \
        np.repeat(rng.uniform(1.0, 5.0, (n + 19) // 20), 20)[:n] + rng.normal(0, 0.01, n)
    pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    gap = np.maximum(0.3, 2.5 * 2 * 0.0175 * r)
    centres = np.sort(rng.choice(n, max(1, n // 2), replace=False))
    for window in (1, 2, 4):
        got = line_normals(pts, window, gap, centres)
        want = reference_line_normals(pts, window, gap, centres)
        assert np.array_equal(got, want, equal_nan=True)
