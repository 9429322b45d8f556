"""Factors and noise models: whitening matches the covariance, Jacobians match finite
differences, robust kernels bound a wrong closure's pull."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from factors.noise import MATCH_SIGMA_FLOOR, NoiseError, floored_covariance, gaussian, robust
from factors.scan_match import (
    loop_closure_factor,
    pose2,
    prior_factor,
    scan_match_factor,
    whitened_chi2,
)

A, B = gtsam.symbol("a", 0), gtsam.symbol("a", 1)


def values(Ta: np.ndarray, Tb: np.ndarray) -> gtsam.Values:
    v = gtsam.Values()
    v.insert(A, pose2(Ta))
    v.insert(B, pose2(Tb))
    return v


def retract(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    p = pose2(T).retract(d)
    return np.array([p.x(), p.y(), p.theta()])


@pytest.mark.parametrize("make", [
    lambda: scan_match_factor(A, B, [1.0, 0.2, 0.3], np.diag([1e4, 4e3, 2e4])),
    lambda: loop_closure_factor(A, B, [1.0, 0.2, 0.3], np.diag([1e4, 4e3, 2e4])),
])
def test_jacobians_match_finite_differences(make: object) -> None:
    factor = make()  # type: ignore[operator]
    model = factor.noiseModel()
    base = model.noise() if isinstance(model, gtsam.noiseModel.Robust) else model

    def whitened(v: gtsam.Values) -> np.ndarray:  # Σ^-½ e, without the kernel's weight
        return np.asarray(base.whiten(np.asarray(factor.unwhitenedError(v))))

    rng = np.random.default_rng(0)
    eps = 1e-6
    for _ in range(3):
        Ta = rng.normal(size=3) * [1.0, 1.0, 1.0]
        Tb = retract(Ta, np.array([1.0, 0.2, 0.3]) + rng.normal(size=3) * 0.05)
        J, b = factor.linearize(values(Ta, Tb)).jacobian()
        num = np.zeros((3, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            e_plus = whitened(values(retract(Ta, d[:3]), retract(Tb, d[3:])))
            e_minus = whitened(values(retract(Ta, -d[:3]), retract(Tb, -d[3:])))
            num[:, k] = (e_plus - e_minus) / (2 * eps)
        # a robust kernel rescales the whitened rows by √w(‖Σ^-½ e‖) (IRLS)
        scale = 1.0
        if isinstance(model, gtsam.noiseModel.Robust):
            dist = math.sqrt(model.noise().squaredMahalanobisDistance(
                np.asarray(factor.unwhitenedError(values(Ta, Tb)))))
            scale = math.sqrt(model.robust().weight(dist))
        np.testing.assert_allclose(J, num * scale, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(-b, whitened(values(Ta, Tb)) * scale, rtol=1e-6, atol=1e-9)


def test_whitening_matches_covariance() -> None:
    info = np.array([[2e4, 3e3, 0.0], [3e3, 1e4, 100.0], [0.0, 100.0, 5e4]])
    f = scan_match_factor(A, B, [0.5, 0.0, 0.0], info, cov_scale=2.0)
    cov = floored_covariance(info, MATCH_SIGMA_FLOOR, 2.0)
    err = np.array([0.01, -0.02, 0.003])
    Ta = np.zeros(3)
    Tb = retract(np.array([0.5, 0.0, 0.0]), err)  # an error of exactly err in the tangent
    chi2 = whitened_chi2(f, values(Ta, Tb))
    assert chi2 == pytest.approx(float(err @ np.linalg.solve(cov, err)), rel=1e-4)


def test_covariance_floor_and_cap() -> None:
    cov = floored_covariance(np.diag([1e12, 1e12, 1e12]))
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), MATCH_SIGMA_FLOOR, rtol=1e-3)
    weak = floored_covariance(np.diag([1e4, 1e-6, 1e4]), max_sigmas=[1.0, 1.0, 1.0])
    assert math.sqrt(weak[1, 1]) <= 1.0 + 1e-9
    with pytest.raises(NoiseError):
        floored_covariance(np.full((2, 2), 1.0))
    with pytest.raises(NoiseError):
        gaussian(-np.eye(3))
    with pytest.raises(NoiseError):
        robust(gaussian(np.eye(3)), "nonsense")


def test_robust_kernel_bounds_a_wrong_closure() -> None:
    """A chain of confident steps plus one wrong closure: with the Huber kernel the chain
    bends far less than with a plain Gaussian closure."""

    def solve(kernel: str | None) -> float:
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        X = [gtsam.symbol("a", i) for i in range(11)]
        g.add(prior_factor(X[0], [0.0, 0.0, 0.0]))
        v.insert(X[0], pose2([0.0, 0.0, 0.0]))
        for i in range(10):
            g.add(scan_match_factor(X[i], X[i + 1], [1.0, 0.0, 0.0], np.diag([1e4, 1e4, 1e4])))
            v.insert(X[i + 1], pose2([i + 1.0, 0.0, 0.0]))
        wrong = [12.0, 3.0, 0.0]  # the true relative pose is (10, 0, 0)
        info = np.diag([1e4, 1e4, 1e4])
        if kernel is None:
            g.add(scan_match_factor(X[0], X[10], wrong, info))
        else:
            g.add(loop_closure_factor(X[0], X[10], wrong, info, kernel=kernel))
        est = gtsam.LevenbergMarquardtOptimizer(g, v).optimize()
        p = est.atPose2(X[10])
        return math.hypot(p.x() - 10.0, p.y())

    plain, huber, cauchy = solve(None), solve("huber"), solve("cauchy")
    assert plain > 1.0  # a Gaussian closure drags the end most of the way
    assert huber < 0.5 * plain
    assert cauchy < huber
