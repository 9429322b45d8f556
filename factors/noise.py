"""Noise models for the pose graph: named constants, covariance/information conversion and
robust kernels. Units: metres and radians; Pose2 tangent order (x, y, θ)."""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

#: the first pose of a robot: pinned, but not so hard that a later removal changes nothing
PRIOR_SIGMAS = np.array([1e-3, 1e-3, math.radians(0.05)])
#: smallest uncertainty a scan match may claim (ICP covariances are optimistic)
MATCH_SIGMA_FLOOR = np.array([0.01, 0.01, math.radians(0.2)])
#: Huber threshold (in sigmas) of loop-closure factors
LOOP_HUBER_K = 1.345
#: Cauchy scale (in sigmas), an alternative heavier-tailed kernel
LOOP_CAUCHY_K = 1.0


class NoiseError(ValueError):
    """A covariance or information matrix is not symmetric positive definite."""


def sigmas(sigma_xy_m: float, sigma_theta_rad: float) -> gtsam.noiseModel.Diagonal:
    """Diagonal Pose2 noise with σ_x = σ_y = ``sigma_xy_m`` and σ_θ = ``sigma_theta_rad``."""
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_xy_m, sigma_xy_m, sigma_theta_rad]))


def prior_noise(s: ArrayLike = PRIOR_SIGMAS) -> gtsam.noiseModel.Diagonal:
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(s, dtype=np.float64))


def floored_covariance(information: ArrayLike, floor_sigmas: ArrayLike = MATCH_SIGMA_FLOOR,
                       scale: float = 1.0, max_sigmas: ArrayLike | None = None) -> F64:
    """Covariance Σ = scale · I⁻¹ + diag(floor²), with I the (3×3) information of a match.

    A singular information (a degenerate match) is regularised first; ``max_sigmas`` caps the
    diagonal so a weak direction stays finite.
    """
    info = np.asarray(information, dtype=np.float64)
    if info.shape != (3, 3) or not np.all(np.isfinite(info)):
        raise NoiseError(f"information must be a finite 3×3 matrix, got {info.shape}")
    info = 0.5 * (info + info.T)
    eps = 1e-9 * max(np.trace(info), 1.0)
    cov = scale * np.linalg.inv(info + eps * np.eye(3))
    floor = np.asarray(floor_sigmas, dtype=np.float64)
    cov = cov + np.diag(floor ** 2)
    if max_sigmas is not None:
        cap = np.asarray(max_sigmas, dtype=np.float64) ** 2
        d = np.sqrt(np.minimum(np.diag(cov), cap) / np.diag(cov))
        cov = cov * np.outer(d, d)
    return 0.5 * (cov + cov.T)


def gaussian(covariance: ArrayLike) -> gtsam.noiseModel.Gaussian:
    """Full Gaussian noise from a 3×3 covariance; raises NoiseError unless SPD."""
    cov = np.asarray(covariance, dtype=np.float64)
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise NoiseError("covariance is not positive definite") from None
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def robust(model: gtsam.noiseModel.Base, kernel: str = "huber",
           k: float = LOOP_HUBER_K) -> gtsam.noiseModel.Robust:
    """Wrap a Gaussian model in an M-estimator (``huber``, ``cauchy`` or ``gm``) of width k σ."""
    est: gtsam.noiseModel.mEstimator.Base
    if kernel == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(k)
    elif kernel == "cauchy":
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    elif kernel == "gm":
        est = gtsam.noiseModel.mEstimator.GemanMcClure.Create(k)
    else:
        raise NoiseError(f"unknown robust kernel {kernel!r}")
    return gtsam.noiseModel.Robust.Create(est, model)
