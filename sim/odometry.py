"""Wheel odometry that drifts: the α1–α4 odometry noise model in arc form.

Over one physics step the robot truly moves ``Δs`` along an arc and turns ``Δθ``. The encoders
report

    Δs_m = (1 + ε_s) Δs + n_s,   n_s ~ N(0, α3 |Δs| + α4 |Δθ|)
    Δθ_m = (1 + ε_θ) Δθ + n_θ,   n_θ ~ N(0, α1 |Δθ| + α2 |Δs|)

with α1 [rad²/rad] (rotation noise per radian turned), α2 [rad²/m] (rotation noise per metre
driven), α3 [m²/m] (translation noise per metre), α4 [m²/rad] (translation noise per radian).
The variances grow linearly with the motion (a random walk), unlike the per-step form of
Thrun et al. whose variances grow with its square, so the drift does not depend on the physics
step. ``ε_s`` and ``ε_θ`` are per-robot calibration errors (wheel radius, track width) drawn once;
they make odometry drift systematically as real wheels do. A robot standing still does not drift.
The odometry pose integrates the reports as exact arcs (chord ``Δs sinc(Δθ/2)`` along the
mid-heading):

    x += Δs_m sinc(Δθ_m/2) cos(θ + Δθ_m/2),  y += Δs_m sinc(Δθ_m/2) sin(θ + Δθ_m/2),
    θ += Δθ_m
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.se2 import wrap_angle


@dataclass(frozen=True)
class OdometryNoise:
    alpha1: float = 4e-4   # rad²/rad
    alpha2: float = 1e-4   # rad²/m
    alpha3: float = 1e-4   # m²/m
    alpha4: float = 1e-5   # m²/rad
    scale_sigma: float = 0.005        # σ of ε_s (distance scale error)
    turn_scale_sigma: float = 0.01    # σ of ε_θ (rotation scale error)

    def draw_bias(self, rng: np.random.Generator) -> tuple[float, float]:
        """(ε_s, ε_θ) for one robot."""
        e = rng.standard_normal(2)
        return float(e[0] * self.scale_sigma), float(e[1] * self.turn_scale_sigma)

    def measure(self, rng: np.random.Generator, ds_m: np.ndarray | float,
                dtheta_rad: np.ndarray | float,
                bias: tuple[np.ndarray | float, np.ndarray | float] = (0.0, 0.0)
                ) -> tuple[np.ndarray, np.ndarray]:
        """Noisy (Δs_m, Δθ_m) for true increments (arrays of any one shape)."""
        ds = np.asarray(ds_m, dtype=np.float64)
        dth = np.asarray(dtheta_rad, dtype=np.float64)
        n = rng.standard_normal((2, *ds.shape))
        var_s = self.alpha3 * np.abs(ds) + self.alpha4 * np.abs(dth)
        var_th = self.alpha1 * np.abs(dth) + self.alpha2 * np.abs(ds)
        return ((1.0 + bias[0]) * ds + np.sqrt(var_s) * n[0],
                (1.0 + bias[1]) * dth + np.sqrt(var_th) * n[1])

    def increment(self, ds_m: float, dtheta_rad: float, bias: tuple[float, float],
                  z: np.ndarray) -> tuple[float, float]:
        """``measure`` for one step with the two standard normals ``z`` drawn beforehand."""
        var_s = self.alpha3 * abs(ds_m) + self.alpha4 * abs(dtheta_rad)
        var_th = self.alpha1 * abs(dtheta_rad) + self.alpha2 * abs(ds_m)
        return ((1.0 + bias[0]) * ds_m + math.sqrt(var_s) * float(z[0]),
                (1.0 + bias[1]) * dtheta_rad + math.sqrt(var_th) * float(z[1]))

    def covariance(self, ds_m: float, dtheta_rad: float) -> np.ndarray:
        """2x2 covariance of (n_s, n_θ) for one step."""
        return np.diag([self.alpha3 * abs(ds_m) + self.alpha4 * abs(dtheta_rad),
                        self.alpha1 * abs(dtheta_rad) + self.alpha2 * abs(ds_m)])


def integrate(pose: np.ndarray, ds_m: np.ndarray | float, dtheta_rad: np.ndarray | float
              ) -> np.ndarray:
    """Advance (..., 3) poses along arcs of length ``ds_m`` turning ``dtheta_rad``."""
    p = np.asarray(pose, dtype=np.float64)
    dth = np.asarray(dtheta_rad, dtype=np.float64)
    mid = p[..., 2] + 0.5 * dth
    chord = ds_m * np.sinc(dth / (2 * np.pi))
    out = np.empty_like(p)
    out[..., 0] = p[..., 0] + chord * np.cos(mid)
    out[..., 1] = p[..., 1] + chord * np.sin(mid)
    out[..., 2] = wrap_angle(np.asarray(p[..., 2] + dth))   # an array even for one pose
    return out
