"""Rendezvous factors: analytic Jacobians against numerical ones, the direct method, and a
joint optimisation that recovers the transform between two robots' frames."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from factors.noise import NoiseError
from factors.rendezvous import (
    Sighting,
    direct_transform,
    fuse_transforms,
    mutual_rendezvous_factor,
    rendezvous_factor,
    sighting_error,
    transform_covariance,
)
from factors.scan_match import pose2, prior_factor
from schemas.se2 import between, compose, inverse, wrap_angle

A, B = gtsam.symbol("a", 3), gtsam.symbol("b", 7)


def exact_sighting(P_o: np.ndarray, P_b: np.ndarray, sr: float = 0.02, sb: float = 0.01,
                   sy: float = 0.05) -> Sighting:
    rel = between(P_o, P_b)
    return Sighting(math.hypot(rel[0], rel[1]), math.atan2(rel[1], rel[0]), rel[2], sr, sb, sy)


def values(**poses: np.ndarray) -> gtsam.Values:
    v = gtsam.Values()
    for name, T in poses.items():
        v.insert(gtsam.symbol(name[0], int(name[1:])), pose2(T))
    return v


def numerical_jacobians(f: gtsam.CustomFactor, v: gtsam.Values, eps: float = 1e-6
                        ) -> list[np.ndarray]:
    out = []
    e0 = np.asarray(f.unwhitenedError(v))
    for key in list(f.keys()):
        J = np.zeros((len(e0), 3))
        for i in range(3):
            d = np.zeros(3)
            d[i] = eps
            vp = gtsam.Values(v)
            vp.update(key, v.atPose2(key).retract(d))
            vm = gtsam.Values(v)
            vm.update(key, v.atPose2(key).retract(-d))
            ep, em = np.asarray(f.unwhitenedError(vp)), np.asarray(f.unwhitenedError(vm))
            J[:, i] = (ep - em) / (2 * eps)
        out.append(J)
    return out


def analytic_jacobians(f: gtsam.CustomFactor, v: gtsam.Values) -> list[np.ndarray]:
    lin = f.linearize(v)
    Ab = lin.jacobian()[0]
    # undo whitening: the factor's noise is diagonal (kernel off in these tests)
    sig = np.asarray(f.noiseModel().sigmas())
    Ab = Ab * sig[:, None]
    return [Ab[:, :3], Ab[:, 3:6]]


@pytest.mark.parametrize("seed", range(6))
def test_single_sighting_jacobians_match_numerical(seed: int) -> None:
    rng = np.random.default_rng(seed)
    X_o, X_b = rng.normal(size=3) * [4, 4, 2], rng.normal(size=3) * [4, 4, 2]
    off_o, off_b = rng.normal(size=3) * [0.3, 0.3, 0.3], rng.normal(size=3) * [0.3, 0.3, 0.3]
    s = exact_sighting(compose(X_o, off_o), compose(X_b, off_b))
    # evaluate away from the measurement, where the error is not zero
    f = rendezvous_factor(A, B, Sighting(s.range_m + 0.3, s.bearing_rad - 0.2, s.yaw_rad + 0.4,
                                         0.02, 0.01, 0.05), off_o, off_b, kernel=None)
    v = gtsam.Values()
    v.insert(A, pose2(X_o))
    v.insert(B, pose2(X_b))
    for Ja, Jn in zip(analytic_jacobians(f, v), numerical_jacobians(f, v), strict=True):
        np.testing.assert_allclose(Ja, Jn, atol=1e-5)
    e = np.asarray(f.unwhitenedError(v))
    np.testing.assert_allclose(e, [-0.3, 0.2, -0.4], atol=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_mutual_jacobians_match_numerical(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    X_a, X_b = rng.normal(size=3) * [3, 3, 2], rng.normal(size=3) * [3, 3, 2]
    offs = [rng.normal(size=3) * 0.2 for _ in range(4)]
    ab = exact_sighting(compose(X_a, offs[0]), compose(X_b, offs[2]))
    ba = exact_sighting(compose(X_b, offs[3]), compose(X_a, offs[1]))
    f = mutual_rendezvous_factor(A, B, ab, ba, (offs[0], offs[1]), (offs[2], offs[3]),
                                 kernel=None)
    v = gtsam.Values()
    v.insert(A, pose2(X_a))
    v.insert(B, pose2(np.add(X_b, [0.2, -0.1, 0.1])))
    for Ja, Jn in zip(analytic_jacobians(f, v), numerical_jacobians(f, v), strict=True):
        np.testing.assert_allclose(Ja, Jn, atol=1e-5)
    v.update(B, pose2(X_b))
    np.testing.assert_allclose(np.asarray(f.unwhitenedError(v)), 0.0, atol=1e-9)


def test_bearing_and_yaw_errors_wrap() -> None:
    e, _, _ = sighting_error([0, 0, 0], [-2.0, 1e-9, math.pi - 1e-3], [0, 0, 0], [0, 0, 0],
                             [2.0, -math.pi + 1e-3, -math.pi + 1e-3])
    assert np.all(np.abs(e) < 1e-2)


def test_direct_transform_recovers_frames() -> None:
    T_AB = np.array([3.0, -2.0, 0.7])            # B's map frame in A's
    P_b_in_B = np.array([1.0, 2.0, -0.4])
    P_b_in_A = compose(T_AB, P_b_in_B)
    P_o_in_A = np.array([-1.0, 0.5, 0.2])
    s = exact_sighting(P_o_in_A, P_b_in_A)
    np.testing.assert_allclose(direct_transform(P_o_in_A, s, P_b_in_B), T_AB, atol=1e-9)
    cov = transform_covariance(P_o_in_A, s, P_b_in_B)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_transform_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(3)
    P_o, P_b = np.array([0.0, 0.0, 0.3]), np.array([1.0, -1.0, 2.0])
    T_AB = np.array([2.0, 1.0, 0.5])
    s = exact_sighting(P_o, compose(T_AB, P_b), 0.05, 0.03, 0.1)
    ps = np.array([0.02, 0.02, 0.01])
    samples = []
    for _ in range(4000):
        z = Sighting(s.range_m + rng.normal() * s.sigma_range_m,
                     s.bearing_rad + rng.normal() * s.sigma_bearing_rad,
                     s.yaw_rad + rng.normal() * s.sigma_yaw_rad, 1, 1, 1)
        Po = compose(P_o, rng.normal(size=3) * ps)
        Pb = compose(P_b, rng.normal(size=3) * ps)
        samples.append(direct_transform(Po, z, Pb))
    emp = np.cov(np.array(samples).T)
    cov = transform_covariance(P_o, s, P_b, ps)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(emp)), rtol=0.1)


def test_fuse_transforms_weights_by_information() -> None:
    m, cov = fuse_transforms([[0.0, 0.0, math.pi - 0.01], [1.0, 0.0, -math.pi + 0.01]],
                             [np.eye(3) * 0.01, np.eye(3) * 0.01])
    np.testing.assert_allclose(m[:2], [0.5, 0.0], atol=1e-9)
    assert abs(abs(m[2]) - math.pi) < 1e-6
    np.testing.assert_allclose(cov, np.eye(3) * 0.005, atol=1e-12)


def test_bad_sightings_are_refused() -> None:
    with pytest.raises(NoiseError):
        Sighting(float("nan"), 0, 0, 0.1, 0.1, 0.1)
    with pytest.raises(NoiseError):
        Sighting(1.0, 0, 0, 0.0, 0.1, 0.1)
    with pytest.raises(NoiseError):
        rendezvous_factor(A, A, Sighting(1.0, 0, 0, 0.1, 0.1, 0.1))


def test_joint_optimisation_recovers_the_transform_and_resists_an_outlier() -> None:
    """Two short trajectories in their own frames, three sightings (one wrong by 2 m): the
    robust joint solution puts B's frame where it is."""
    T_AB = np.array([4.0, 1.0, 1.2])
    truth_a = [np.array([0.5 * i, 0.0, 0.0]) for i in range(6)]
    truth_b_in_B = [np.array([0.0, 0.4 * i, 0.3]) for i in range(6)]
    g = gtsam.NonlinearFactorGraph()
    init = gtsam.Values()
    ka = [gtsam.symbol("a", i) for i in range(6)]
    kb = [gtsam.symbol("b", i) for i in range(6)]
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.005]))
    g.add(prior_factor(ka[0], truth_a[0]))
    for k, tr in ((ka, truth_a), (kb, truth_b_in_B)):
        for i in range(5):
            g.add(gtsam.BetweenFactorPose2(k[i], k[i + 1], pose2(between(tr[i], tr[i + 1])),
                                           noise))
    for i in range(6):
        init.insert(ka[i], pose2(truth_a[i]))
        init.insert(kb[i], pose2(truth_b_in_B[i]))  # B starts in its own frame: far off
    for i in (1, 3, 5):
        s = exact_sighting(truth_a[i], compose(T_AB, truth_b_in_B[i]))
        if i == 3:
            s = Sighting(s.range_m + 2.0, s.bearing_rad, s.yaw_rad, 0.02, 0.01, 0.03)
        else:
            s = Sighting(s.range_m, s.bearing_rad, s.yaw_rad, 0.02, 0.01, 0.03)
        g.add(rendezvous_factor(ka[i], kb[i], s, kernel="cauchy", k=1.0))
    # initialise B by the direct method from the first sighting
    s1 = exact_sighting(truth_a[1], compose(T_AB, truth_b_in_B[1]))
    T0 = direct_transform(truth_a[1], s1, truth_b_in_B[1])
    for i in range(6):
        init.update(kb[i], pose2(compose(T0, truth_b_in_B[i])))
    est = gtsam.LevenbergMarquardtOptimizer(g, init).optimize()
    got = est.atPose2(kb[0])
    want = compose(T_AB, truth_b_in_B[0])
    assert math.hypot(got.x() - want[0], got.y() - want[1]) < 0.05
    assert abs(wrap_angle(got.theta() - want[2])) < math.radians(1)
    np.testing.assert_allclose(inverse(inverse(T_AB)), T_AB, atol=1e-12)


def test_rendezvous_factors_pickle_as_the_call_that_made_them() -> None:
    """The server's snapshots pickle its graphs: a sighting factor comes back with the same
    keys, noise and error."""
    import pickle

    import gtsam

    from factors.rendezvous import Sighting, mutual_rendezvous_factor, rendezvous_factor

    s = Sighting(2.0, 0.1, 3.0, 0.05, 0.01, 0.1)
    v = gtsam.Values()
    v.insert(1, gtsam.Pose2(0.1, -0.2, 0.3))
    v.insert(2, gtsam.Pose2(2.0, 0.4, -2.9))
    for f in (rendezvous_factor(1, 2, s, (0.1, 0.0, 0.05), (0.0, 0.2, 0.0)),
              mutual_rendezvous_factor(1, 2, s, s)):
        g = pickle.loads(pickle.dumps(f))
        assert list(g.keys()) == [1, 2] and g.error(v) == f.error(v) > 0
