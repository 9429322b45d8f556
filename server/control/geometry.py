"""Velocity commands and the small planar geometry the controllers share."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray


class Twist(NamedTuple):
    """A velocity command for a differential-drive base: forward v [m/s], yaw rate ω [rad/s]."""

    v_mps: float
    omega_rps: float


STOP = Twist(0.0, 0.0)


def world_to_robot(pose: ArrayLike, xy_world: ArrayLike) -> NDArray[np.float64]:
    """Points (…, 2) from the world frame into the frame of a robot at pose (x, y, θ):
    p_robot = R(θ)ᵀ (p_world − t)."""
    x, y, th = (float(v) for v in np.asarray(pose, np.float64).reshape(3))
    p = np.asarray(xy_world, np.float64)
    dx, dy = p[..., 0] - x, p[..., 1] - y
    c, s = math.cos(th), math.sin(th)
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


def clip(value: float, limit: float) -> float:
    """value clipped to [−limit, limit]."""
    return max(-limit, min(limit, value))
