"""Keyframe-to-keyframe measurements: a scan's match, placed between two keyframes, as a factor.

A match gives the new keyframe's pose in the map frame with an information matrix in that
frame; the graph wants the relative pose between two keyframes, with an information in the
frame of the second. The match's information is rotated into it, and the odometry's is added:
a degenerate match (a featureless corridor) says nothing along the corridor, and without the
odometry's share that direction would be free in the graph.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.scan_match import scan_match_factor
from schemas.se2 import pose_distance
from server.slam.config import GraphConfig
from server.slam.frontend import FrontendMatch, MatchKind

F64 = NDArray[np.float64]


def rotation_xyt(theta_rad: float) -> F64:
    """The 3×3 rotation of (x, y, θ) vectors by ``theta_rad``."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def odometry_only(match: FrontendMatch) -> FrontendMatch:
    """The same pose, carrying no information of its own: a factor from it is odometry's."""
    return FrontendMatch(match.T_map_robot, MatchKind.ODOMETRY, np.zeros((3, 3)), 0.0)


def relative_information(match: FrontendMatch, T_a_b: F64, cfg: GraphConfig) -> F64:
    """Information (3×3) of the relative pose ``T_a_b`` measured by ``match`` (which placed
    b), in b's frame: the match's, rotated from the map frame, plus odometry's over the step,
    whose σ grows with it: σ_xy = k_m·d + floor_m, σ_θ = k_deg·|Δθ| + floor_deg."""
    A = rotation_xyt(match.T_map_robot[2])
    info = A.T @ match.information @ A if match.kind != MatchKind.ODOMETRY else np.zeros((3, 3))
    d, a = pose_distance(T_a_b)
    s_xy = cfg.odometry_sigma_m_per_m * d + cfg.match_sigma_floor_m
    s_th = math.radians(cfg.odometry_sigma_deg_per_rad * a + cfg.match_sigma_floor_deg)
    return info + np.diag([s_xy ** -2, s_xy ** -2, s_th ** -2])


def match_factor(key_a: int, key_b: int, T_a_b: F64, match: FrontendMatch,
                 cfg: GraphConfig) -> gtsam.BetweenFactorPose2:
    """The between-factor of keyframes a and b for ``match`` (see ``relative_information``);
    a match's covariance is scaled by ``match_cov_scale`` and floored, odometry's only
    floored."""
    floor = np.array([cfg.match_sigma_floor_m, cfg.match_sigma_floor_m,
                      math.radians(cfg.match_sigma_floor_deg)])
    scale = cfg.match_cov_scale if match.kind != MatchKind.ODOMETRY else 1.0
    return scan_match_factor(key_a, key_b, T_a_b, relative_information(match, T_a_b, cfg),
                             scale, floor)
