"""Factors a scan-matching front-end adds to a robot's pose graph.

All are ``gtsam.BetweenFactorPose2``/``PriorFactorPose2`` on keys ``gtsam.symbol(c, k)``; the
measured relative pose ``T_i_j`` maps points from keyframe j to keyframe i, and its error is
``Log(T_i_j⁻¹ · (X_i⁻¹ X_j))`` whitened by the match covariance.
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import ArrayLike

from factors.noise import (
    LOOP_HUBER_K,
    MATCH_SIGMA_FLOOR,
    PRIOR_SIGMAS,
    floored_covariance,
    gaussian,
    prior_noise,
    robust,
)


def pose2(T: ArrayLike) -> gtsam.Pose2:
    """``gtsam.Pose2`` from an (x, y, θ) array."""
    x, y, t = (float(v) for v in np.asarray(T, dtype=np.float64))
    return gtsam.Pose2(x, y, t)


def prior_factor(key: int, T_map_robot: ArrayLike,
                 s: ArrayLike = PRIOR_SIGMAS) -> gtsam.PriorFactorPose2:
    """Anchor of a robot's first pose in its map frame."""
    return gtsam.PriorFactorPose2(key, pose2(T_map_robot), prior_noise(s))


def scan_match_factor(key_i: int, key_j: int, T_i_j: ArrayLike, information: ArrayLike,
                      cov_scale: float = 1.0, floor_sigmas: ArrayLike = MATCH_SIGMA_FLOOR,
                      max_sigmas: ArrayLike | None = None) -> gtsam.BetweenFactorPose2:
    """Between-factor of consecutive keyframes from a scan match with ``information`` (3×3)."""
    cov = floored_covariance(information, floor_sigmas, cov_scale, max_sigmas)
    return gtsam.BetweenFactorPose2(key_i, key_j, pose2(T_i_j), gaussian(cov))


def loop_closure_factor(key_i: int, key_j: int, T_i_j: ArrayLike, information: ArrayLike,
                        cov_scale: float = 1.0, floor_sigmas: ArrayLike = MATCH_SIGMA_FLOOR,
                        kernel: str = "huber", k: float = LOOP_HUBER_K
                        ) -> gtsam.BetweenFactorPose2:
    """Between-factor of a verified loop closure, under a robust kernel: a closure that
    disagrees with the rest of the graph loses weight instead of bending the map."""
    cov = floored_covariance(information, floor_sigmas, cov_scale)
    return gtsam.BetweenFactorPose2(key_i, key_j, pose2(T_i_j), robust(gaussian(cov), kernel, k))


#: σ of the position part of a heading-only tie: large enough to say nothing about it
FREE_SIGMA_M = 1e3


def heading_factor(key_i: int, key_j: int, T_i_j: ArrayLike, sigma_rad: float,
                   huber_k: float = LOOP_HUBER_K) -> gtsam.BetweenFactorPose2:
    """Between-factor that ties only the heading of key j relative to key i (``T_i_j[2]``):
    its position part (``T_i_j[:2]``, the current estimate) has a σ of ``FREE_SIGMA_M``.
    Under a Huber kernel."""
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([FREE_SIGMA_M, FREE_SIGMA_M, sigma_rad]))
    return gtsam.BetweenFactorPose2(key_i, key_j, pose2(T_i_j), robust(noise, "huber", huber_k))


def whitened_chi2(factor: gtsam.NoiseModelFactor, values: gtsam.Values) -> float:
    """Squared Mahalanobis norm of a between factor's error at ``values`` (without the kernel)."""
    err = np.asarray(factor.unwhitenedError(values), dtype=np.float64)
    model = factor.noiseModel()
    if isinstance(model, gtsam.noiseModel.Robust):
        model = model.noise()
    w = np.asarray(model.whiten(err), dtype=np.float64)
    return float(w @ w)
