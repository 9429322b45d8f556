"""Inter-robot factors from tag sightings (rendezvous).

A sighting says where the observed robot was, seen from the observer, at one instant:
range ``r``, bearing ``b`` (in the observer's base frame) and the observed robot's heading
relative to the observer's, ``yaw``. The graph holds keyframes, not every instant, so each
sighting carries two fixed offsets: ``T_kf_o`` (the observer at the sighting, relative to its
keyframe) and ``T_kf_b`` (the observed robot, relative to its keyframe). With keyframe poses
``X_o`` and ``X_b`` the predicted measurement is

    rel = (X_o · T_kf_o)⁻¹ · (X_b · T_kf_b),   h(rel) = (|t_rel|, atan2(t_rel), θ_rel)

and the error ``h(rel) − z`` (angles wrapped) is whitened by the sighting's own
(σ_range, σ_bearing, σ_yaw), under a robust kernel. The mutual factor stacks the two sightings
of a pair of robots that saw each other (each from its own side). Jacobians are analytic
(GTSAM's right-perturbation convention on Pose2) and checked numerically in the tests.

``direct_transform`` is the one-shot alternative: the transform between two robots' map frames
from a single sighting, ``T = T_c · T_r · T_o⁻¹``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.noise import NoiseError, robust
from schemas.se2 import adjoint, between, compose, inverse, wrap_angle

F64 = NDArray[np.float64]

#: Huber width (in sigmas) of rendezvous factors
RENDEZVOUS_HUBER_K = 1.345
#: default uncertainty of each robot's own pose at a sighting (x, y, θ)
POSE_SIGMAS = (0.02, 0.02, math.radians(0.5))


@dataclass(frozen=True)
class Sighting:
    """One tag sighting, observer → observed; sigmas are standard deviations."""

    range_m: float
    bearing_rad: float
    yaw_rad: float
    sigma_range_m: float
    sigma_bearing_rad: float
    sigma_yaw_rad: float

    def __post_init__(self) -> None:
        vals = (self.range_m, self.bearing_rad, self.yaw_rad, self.sigma_range_m,
                self.sigma_bearing_rad, self.sigma_yaw_rad)
        if not all(math.isfinite(v) for v in vals):
            raise NoiseError(f"sighting values must be finite, got {vals}")
        if self.range_m <= 0:
            raise NoiseError(f"sighting range must be positive, got {self.range_m}")
        if min(vals[3:]) <= 0:
            raise NoiseError(f"sighting sigmas must be positive, got {vals[3:]}")

    @property
    def z(self) -> F64:
        return np.array([self.range_m, self.bearing_rad, self.yaw_rad])

    @property
    def sigmas(self) -> F64:
        return np.array([self.sigma_range_m, self.sigma_bearing_rad, self.sigma_yaw_rad])

    def relative_pose(self) -> F64:
        """The observed robot in the observer's frame, (x, y, θ)."""
        return np.array([self.range_m * math.cos(self.bearing_rad),
                         self.range_m * math.sin(self.bearing_rad), self.yaw_rad])

    def relative_covariance(self) -> F64:
        """Covariance (3×3) of ``relative_pose`` to first order."""
        c, s, r = math.cos(self.bearing_rad), math.sin(self.bearing_rad), self.range_m
        J = np.array([[c, -r * s, 0.0], [s, r * c, 0.0], [0.0, 0.0, 1.0]])
        return J @ np.diag(self.sigmas ** 2) @ J.T


def direct_transform(T_c: ArrayLike, sighting: Sighting | ArrayLike, T_o: ArrayLike) -> F64:
    """``T = T_c · T_r · T_o⁻¹``: maps the observed robot's map frame into the observer's.

    ``T_c``: the observer's pose in its map frame, ``T_r``: the observed robot relative to the
    observer (a ``Sighting`` or an (x, y, θ) pose), ``T_o``: the observed robot's pose in its own
    map frame, all at the sighting's instant."""
    T_r = sighting.relative_pose() if isinstance(sighting, Sighting) else np.asarray(sighting)
    return compose(compose(T_c, T_r), inverse(T_o))


def predict(rel: ArrayLike) -> tuple[F64, F64]:
    """h(rel) = (range, bearing, yaw) and its Jacobian (3×3) w.r.t. a right perturbation."""
    x, y, t = np.asarray(rel, dtype=np.float64)
    r2 = max(x * x + y * y, 1e-12)
    r = math.sqrt(r2)
    c, s = math.cos(t), math.sin(t)
    R = np.array([[c, -s], [s, c]])
    J = np.zeros((3, 3))
    J[0, :2] = np.array([x, y]) / r @ R
    J[1, :2] = np.array([-y, x]) / r2 @ R
    J[2, 2] = 1.0
    return np.array([r, math.atan2(y, x), t]), J


def sighting_error(X_o: ArrayLike, X_b: ArrayLike, T_kf_o: ArrayLike, T_kf_b: ArrayLike,
                   z: ArrayLike) -> tuple[F64, F64, F64]:
    """Error h(rel) − z of one sighting and its Jacobians w.r.t. X_o and X_b."""
    P_o = compose(X_o, T_kf_o)
    P_b = compose(X_b, T_kf_b)
    rel = between(P_o, P_b)
    h, Jh = predict(rel)
    zz = np.asarray(z, dtype=np.float64)
    e = np.array([h[0] - zz[0], wrap_angle(h[1] - zz[1]), wrap_angle(h[2] - zz[2])])
    H_o = Jh @ (-adjoint(inverse(rel))) @ adjoint(inverse(T_kf_o))
    H_b = Jh @ adjoint(inverse(T_kf_b))
    return e, H_o, H_b


def _xyt(p: gtsam.Pose2) -> F64:
    return np.array([p.x(), p.y(), p.theta()])


def _noise(sigmas: F64, kernel: str | None, k: float) -> gtsam.noiseModel.Base:
    model = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))
    return model if kernel is None else robust(model, kernel, k)


class RecipeFactor(gtsam.CustomFactor):
    """A CustomFactor that pickles as the call that made it (its error function is a closure,
    which cannot be pickled): the server's snapshots hold these."""

    def __init__(self, noise: gtsam.noiseModel.Base, keys: list[int],
                 error: Any, recipe: tuple[Any, tuple[Any, ...]]) -> None:
        super().__init__(noise, keys, error)
        self._recipe = recipe

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return self._recipe


def rendezvous_factor(key_observer: int, key_observed: int, sighting: Sighting,
                      T_kf_observer: ArrayLike = (0.0, 0.0, 0.0),
                      T_kf_observed: ArrayLike = (0.0, 0.0, 0.0), kernel: str | None = "huber",
                      k: float = RENDEZVOUS_HUBER_K) -> gtsam.CustomFactor:
    """Factor of one sighting between the observer's and the observed robot's keyframes."""
    if key_observer == key_observed:
        raise NoiseError("a rendezvous factor needs two different keys")
    A = np.asarray(T_kf_observer, dtype=np.float64)
    B = np.asarray(T_kf_observed, dtype=np.float64)
    z = sighting.z

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[F64] | None) -> F64:
        X_o = _xyt(v.atPose2(this.keys()[0]))
        X_b = _xyt(v.atPose2(this.keys()[1]))
        e, H_o, H_b = sighting_error(X_o, X_b, A, B, z)
        if H is not None:
            H[0] = H_o
            H[1] = H_b
        return e

    return RecipeFactor(_noise(sighting.sigmas, kernel, k), [key_observer, key_observed], error,
                        (rendezvous_factor, (key_observer, key_observed, sighting, A, B,
                                             kernel, k)))


def mutual_rendezvous_factor(key_a: int, key_b: int, a_sees_b: Sighting, b_sees_a: Sighting,
                             T_kf_a: tuple[ArrayLike, ArrayLike] = ((0, 0, 0), (0, 0, 0)),
                             T_kf_b: tuple[ArrayLike, ArrayLike] = ((0, 0, 0), (0, 0, 0)),
                             kernel: str | None = "huber", k: float = RENDEZVOUS_HUBER_K
                             ) -> gtsam.CustomFactor:
    """One 6-row factor for two robots that saw each other: A's sighting of B and B's of A.

    ``T_kf_a`` = (offset of A at A's sighting, offset of A at B's sighting) relative to A's
    keyframe; ``T_kf_b`` likewise for B."""
    if key_a == key_b:
        raise NoiseError("a rendezvous factor needs two different keys")
    a1, a2 = (np.asarray(t, dtype=np.float64) for t in T_kf_a)
    b1, b2 = (np.asarray(t, dtype=np.float64) for t in T_kf_b)
    z1, z2 = a_sees_b.z, b_sees_a.z

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[F64] | None) -> F64:
        X_a = _xyt(v.atPose2(this.keys()[0]))
        X_b = _xyt(v.atPose2(this.keys()[1]))
        e1, Ha1, Hb1 = sighting_error(X_a, X_b, a1, b1, z1)
        e2, Hb2, Ha2 = sighting_error(X_b, X_a, b2, a2, z2)
        if H is not None:
            H[0] = np.vstack([Ha1, Ha2])
            H[1] = np.vstack([Hb1, Hb2])
        return np.concatenate([e1, e2])

    sig = np.concatenate([a_sees_b.sigmas, b_sees_a.sigmas])
    return RecipeFactor(_noise(sig, kernel, k), [key_a, key_b], error,
                        (mutual_rendezvous_factor, (key_a, key_b, a_sees_b, b_sees_a, T_kf_a,
                                                    T_kf_b, kernel, k)))


def fuse_transforms(transforms: Sequence[ArrayLike], covariances: Sequence[ArrayLike]
                    ) -> tuple[F64, F64]:
    """Information-weighted mean of several estimates of one transform (angles averaged on
    the circle about the first), and the covariance of the mean."""
    if not transforms:
        raise NoiseError("nothing to fuse")
    Ts = np.array([np.asarray(t, dtype=np.float64) for t in transforms])
    ref = Ts[0, 2]
    Ts[:, 2] = ref + np.array([wrap_angle(t - ref) for t in Ts[:, 2]])
    infos = [np.linalg.inv(np.asarray(c, dtype=np.float64)) for c in covariances]
    info = np.sum(infos, axis=0)
    cov = np.linalg.inv(info)
    mean = cov @ np.sum([w @ T for w, T in zip(infos, Ts, strict=True)], axis=0)
    mean[2] = wrap_angle(mean[2])
    return mean, 0.5 * (cov + cov.T)


def transform_covariance(T_c: ArrayLike, sighting: Sighting, T_o: ArrayLike,
                         pose_sigmas: ArrayLike = POSE_SIGMAS) -> F64:
    """First-order covariance of ``direct_transform``: the sighting's own plus both robots'
    pose uncertainty (``pose_sigmas``, each), in (x, y, θ) coordinates of the transform."""
    T_o = np.asarray(T_o, dtype=np.float64)
    T_r = sighting.relative_pose()
    # the sighting's covariance in T_r's right-perturbation tangent (rotate xy into T_r)
    c, s = math.cos(T_r[2]), math.sin(T_r[2])
    Rt = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    cov_r = Rt @ sighting.relative_covariance() @ Rt.T
    # T = T_c·T_r·T_o⁻¹, each factor perturbed on the right, mapped to T's right perturbation
    ps = np.diag(np.asarray(pose_sigmas, dtype=np.float64) ** 2)
    A_c = adjoint(inverse(compose(T_r, inverse(T_o))))
    A_r = adjoint(T_o)
    A_o = -adjoint(T_o)
    cov = A_c @ ps @ A_c.T + A_r @ cov_r @ A_r.T + A_o @ ps @ A_o.T
    # and into plain (x, y, θ) coordinates of T (what ``fuse_transforms`` averages)
    t = direct_transform(T_c, sighting, T_o)[2]
    J = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0],
                  [0.0, 0.0, 1.0]])
    cov = J @ cov @ J.T
    return 0.5 * (cov + cov.T)
