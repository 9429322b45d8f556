"""Small pose helpers: 4x4 homogeneous transforms (planar poses (x, y, theta) are in
``schemas.se2``)."""

from __future__ import annotations

import math

import numpy as np

from schemas.se2 import between


def between2(a: tuple[float, float, float], b: tuple[float, float, float]
             ) -> tuple[float, float, float]:
    """``schemas.se2.between`` on tuples: pose ``b`` expressed in frame ``a``."""
    x, y, t = between(a, b).tolist()
    return x, y, t


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (SDF's fixed-axis roll-pitch-yaw)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def quat_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Rotation of the unit quaternion (x, y, z, w); the quaternion is normalised first."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if n == 0.0:
        raise ValueError("zero quaternion")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def transform(R: np.ndarray, t: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def planar_transform(pose: tuple[float, float, float]) -> np.ndarray:
    """4x4 transform of a planar pose (the frame sits on the floor, z = 0)."""
    return transform(rpy_matrix(0.0, 0.0, pose[2]), (pose[0], pose[1], 0.0))


def inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out

