"""SE(2): planar poses ``(x, y, θ)`` on numpy arrays — the project's one copy of these helpers.

Convention: θ in radians, always wrapped to (−π, π]. A pose ``T_a_b = (x, y, θ)`` maps points
from frame b into frame a: ``p_a = R(θ) p_b + (x, y)``; ``compose(T_a_b, T_b_c) = T_a_c``.
``compose``, ``inverse``, ``between`` and ``adjoint`` accept a single pose of shape (3,) or a
stack of shape (N, 3). A single pose is computed with plain floats (``math``), a stack with
numpy; both give angles in the same interval.

This module sits at the bottom of the stack: it imports nothing from the project.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

__all__ = ["F64", "adjoint", "between", "compose", "inverse", "pose_distance", "rotate_vectors",
           "transform_points", "wrap_angle"]


def _wrap1(t: float) -> float:
    """One angle [rad] wrapped to (−π, π] (``math.remainder`` is exact)."""
    w = math.remainder(t, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


def _wrapn(t: NDArray[Any]) -> F64:
    """Angles [rad] wrapped to (−π, π], elementwise."""
    w = np.mod(t + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


@overload
def wrap_angle(theta: float) -> float: ...
@overload
def wrap_angle(theta: NDArray[Any] | Sequence[float]) -> F64: ...
def wrap_angle(theta: ArrayLike) -> float | F64:
    """Angle(s) [rad] wrapped to (−π, π]: a scalar gives a float, an array (or list) an array."""
    if isinstance(theta, (int, float, np.integer, np.floating)):
        return _wrap1(float(theta))
    return _wrapn(np.asarray(theta, dtype=np.float64))


def compose(T_a_b: ArrayLike, T_b_c: ArrayLike) -> F64:
    """``T_a_c = T_a_b ⊕ T_b_c``: t_ac = t_ab + R(θ_ab) t_bc, θ_ac = θ_ab + θ_bc."""
    a = np.asarray(T_a_b, dtype=np.float64)
    b = np.asarray(T_b_c, dtype=np.float64)
    if a.shape == (3,) and b.shape == (3,):  # one pose: plain floats are ~10× faster
        ax, ay, at = a.tolist()
        bx, by, bt = b.tolist()
        c1, s1 = math.cos(at), math.sin(at)
        return np.array([ax + c1 * bx - s1 * by, ay + s1 * bx + c1 * by, _wrap1(at + bt)])
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, _wrapn(a[..., 2] + b[..., 2])], axis=-1)


def inverse(T_a_b: ArrayLike) -> F64:
    """``T_b_a = T_a_b⁻¹``: t_ba = −R(θ)ᵀ t_ab, θ_ba = −θ_ab."""
    a = np.asarray(T_a_b, dtype=np.float64)
    if a.shape == (3,):
        ax, ay, at = a.tolist()
        c1, s1 = math.cos(at), math.sin(at)
        return np.array([-(c1 * ax + s1 * ay), s1 * ax - c1 * ay, _wrap1(-at)])
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, _wrapn(-a[..., 2])], axis=-1)


def between(T_w_a: ArrayLike, T_w_b: ArrayLike) -> F64:
    """``T_a_b = T_w_a⁻¹ ⊕ T_w_b`` (the relative pose of b seen from a)."""
    return compose(inverse(T_w_a), T_w_b)


def adjoint(T_a_b: ArrayLike) -> F64:
    """Adjoint of a pose for tangent vectors (vx, vy, ω), GTSAM's ``Pose2.AdjointMap``:
    ``[[c, −s, y], [s, c, −x], [0, 0, 1]]``. Shape (3, 3), or (N, 3, 3) for a stack."""
    a = np.asarray(T_a_b, dtype=np.float64)
    if a.shape == (3,):
        x, y, t = a.tolist()
        c, s = math.cos(t), math.sin(t)
        return np.array([[c, -s, y], [s, c, -x], [0.0, 0.0, 1.0]])
    cv, sv = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.zeros((*a.shape[:-1], 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = cv, -sv, a[..., 1]
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = sv, cv, -a[..., 0]
    out[..., 2, 2] = 1.0
    return out


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> F64:
    """Map (N, 2) points from frame b to frame a: ``p_a = R(θ) p_b + t``."""
    T = np.asarray(T_a_b, dtype=np.float64)
    p = np.asarray(points_b, dtype=np.float64)
    c, s = np.cos(T[2]), np.sin(T[2])
    out = np.empty_like(p)
    out[:, 0] = c * p[:, 0] - s * p[:, 1] + T[0]
    out[:, 1] = s * p[:, 0] + c * p[:, 1] + T[1]
    return out


def rotate_vectors(theta: float, vectors: ArrayLike) -> F64:
    """Rotate (N, 2) direction vectors (e.g. normals) by ``theta`` [rad]."""
    v = np.asarray(vectors, dtype=np.float64)
    c, s = np.cos(theta), np.sin(theta)
    out = np.empty_like(v)
    out[:, 0] = c * v[:, 0] - s * v[:, 1]
    out[:, 1] = s * v[:, 0] + c * v[:, 1]
    return out


def pose_distance(T_a_b: ArrayLike) -> tuple[float, float]:
    """Translation [m] and absolute rotation [rad] of a relative pose."""
    x, y, t = np.asarray(T_a_b, dtype=np.float64).tolist()
    return math.hypot(x, y), abs(_wrap1(t))
