"""Properties of schemas.se2 (the one SE(2) module), checked with hypothesis."""

from __future__ import annotations

import math

import gtsam
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from schemas.se2 import (
    adjoint,
    between,
    compose,
    inverse,
    pose_distance,
    rotate_vectors,
    transform_points,
    wrap_angle,
)

coord = st.floats(-100.0, 100.0, allow_nan=False)
angle = st.floats(-20.0, 20.0, allow_nan=False)
poses = st.tuples(coord, coord, angle).map(lambda p: np.array(p, dtype=np.float64))
stacks = st.integers(1, 6).flatmap(lambda n: st.tuples(*[poses] * n).map(np.array))
any_angle = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False),
    st.sampled_from([math.pi, -math.pi, 2 * math.pi, -2 * math.pi, 3 * math.pi, -3 * math.pi,
                     1001 * math.pi, -1001 * math.pi, 0.0, -0.0, math.nextafter(math.pi, 0.0),
                     math.nextafter(-math.pi, 0.0)]),
    st.integers(-1000, 1000).map(lambda k: k * math.pi),
    st.integers(-1000, 1000).map(lambda k: k * 2 * math.pi),
)
IDENTITY = np.zeros(3)


def angle_gap(a: float, b: float) -> float:
    return abs(wrap_angle(a - b))


def assert_pose_close(got: np.ndarray, want: np.ndarray, tol: float = 1e-9) -> None:
    """Poses equal up to ``tol``, angles compared wrapped."""
    scale = max(1.0, float(np.abs(want[..., :2]).max(initial=0.0)))
    np.testing.assert_allclose(got[..., :2], want[..., :2], atol=tol * scale)
    gaps = np.abs(wrap_angle(np.asarray(got[..., 2]) - np.asarray(want[..., 2])))
    assert np.all(gaps <= tol), (got, want)


def in_interval(w: np.ndarray | float) -> bool:
    a = np.asarray(w)
    return bool(np.all((a > -math.pi) & (a <= math.pi)))


# -- wrap_angle ---------------------------------------------------------------------------
@given(any_angle)
def test_wrap_of_a_scalar_is_a_float_in_the_interval_and_idempotent(a: float) -> None:
    w = wrap_angle(a)
    assert type(w) is float
    assert in_interval(w)
    assert wrap_angle(w) == w
    assert angle_gap(w, a) <= 1e-12 * max(1.0, abs(a))   # only whole turns removed
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9 * max(1.0, abs(a)))
    assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9 * max(1.0, abs(a)))


@given(arrays(np.float64, st.integers(0, 8), elements=any_angle))
def test_wrap_of_an_array_is_an_array_in_the_interval_and_idempotent(a: np.ndarray) -> None:
    w = wrap_angle(a)
    assert isinstance(w, np.ndarray) and w.shape == a.shape
    assert in_interval(w)
    np.testing.assert_allclose(wrap_angle(w), w, rtol=0, atol=1e-12)
    assert in_interval(wrap_angle(w))
    for wi, ai in zip(w, a, strict=True):   # the array and scalar paths agree
        assert angle_gap(float(wi), wrap_angle(float(ai))) <= 1e-12 * max(1.0, abs(ai))


def test_wrap_edges() -> None:
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi) == math.pi
    assert wrap_angle(-3 * math.pi) == math.pi
    assert wrap_angle(2 * math.pi) == 0.0
    assert wrap_angle(0) == 0.0 and type(wrap_angle(0)) is float
    assert wrap_angle(np.float64(-math.pi)) == math.pi
    np.testing.assert_array_equal(
        wrap_angle(np.array([math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 0.0])),
        [math.pi, math.pi, math.pi, math.pi, 0.0])
    np.testing.assert_array_equal(wrap_angle([-math.pi]), [math.pi])


# -- compose / inverse / between ----------------------------------------------------------
@given(poses, poses)
def test_compose_with_between_gives_back_the_target(a: np.ndarray, b: np.ndarray) -> None:
    assert_pose_close(compose(a, between(a, b)), b)


@given(poses)
def test_compose_with_inverse_is_identity(a: np.ndarray) -> None:
    assert_pose_close(compose(a, inverse(a)), IDENTITY)
    assert_pose_close(compose(inverse(a), a), IDENTITY)


@given(poses)
def test_inverse_of_inverse(a: np.ndarray) -> None:
    assert_pose_close(inverse(inverse(a)), a)


@given(poses, poses)
def test_results_have_wrapped_angles(a: np.ndarray, b: np.ndarray) -> None:
    for p in (compose(a, b), inverse(a), between(a, b)):
        assert p.shape == (3,) and in_interval(p[2])


@given(poses, poses)
def test_matches_gtsam_pose2(a: np.ndarray, b: np.ndarray) -> None:
    A, B = gtsam.Pose2(*a), gtsam.Pose2(*b)
    for got, P in ((compose(a, b), A.compose(B)), (inverse(a), A.inverse()),
                   (between(a, b), A.between(B))):
        assert_pose_close(got, np.array([P.x(), P.y(), P.theta()]))
    np.testing.assert_allclose(adjoint(a), A.AdjointMap(), atol=1e-9)


@settings(max_examples=50)
@given(stacks, stacks)
def test_a_stack_gives_what_each_pose_gives(a: np.ndarray, b: np.ndarray) -> None:
    n = min(len(a), len(b))
    a, b = a[:n], b[:n]
    c, i, d, ad = compose(a, b), inverse(a), between(a, b), adjoint(a)
    assert c.shape == i.shape == d.shape == (n, 3) and ad.shape == (n, 3, 3)
    assert in_interval(c[:, 2]) and in_interval(i[:, 2]) and in_interval(d[:, 2])
    for k in range(n):
        assert_pose_close(c[k], compose(a[k], b[k]), 1e-12)
        assert_pose_close(i[k], inverse(a[k]), 1e-12)
        assert_pose_close(d[k], between(a[k], b[k]), 1e-12)
        np.testing.assert_allclose(ad[k], adjoint(a[k]), rtol=0, atol=1e-12)
    # one pose with a stack broadcasts
    for k in range(n):
        assert_pose_close(compose(a[0], b)[k], compose(a[0], b[k]), 1e-12)


# -- points, vectors, distance ------------------------------------------------------------
@given(poses, arrays(np.float64, st.tuples(st.integers(0, 6), st.just(2)), elements=coord))
def test_transform_points_agrees_with_compose(T: np.ndarray, pts: np.ndarray) -> None:
    got = transform_points(T, pts)
    assert got.shape == pts.shape
    for p, g in zip(pts, got, strict=True):
        want = compose(T, np.array([p[0], p[1], 0.0]))[:2]
        np.testing.assert_allclose(g, want, rtol=0, atol=1e-9 * max(1.0, np.abs(want).max()))
    back = transform_points(inverse(T), got)
    np.testing.assert_allclose(back, pts, rtol=0, atol=1e-9 * max(1.0, np.abs(T[:2]).max()))


@given(angle, arrays(np.float64, st.tuples(st.integers(0, 6), st.just(2)), elements=coord))
def test_rotate_vectors_is_transform_points_without_translation(
        theta: float, v: np.ndarray) -> None:
    np.testing.assert_allclose(rotate_vectors(theta, v),
                               transform_points(np.array([0.0, 0.0, theta]), v),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.hypot(*rotate_vectors(theta, v).T), np.hypot(*v.T),
                               rtol=1e-12, atol=1e-9)


@given(poses)
def test_pose_distance(a: np.ndarray) -> None:
    d, r = pose_distance(a)
    assert math.isclose(d, math.hypot(a[0], a[1]))
    assert 0.0 <= r <= math.pi and math.isclose(r, abs(wrap_angle(float(a[2]))))
