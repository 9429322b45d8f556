"""A narrow scan's pose, averaged over the latest matches.

One narrow scan of a noisy depth camera pins the heading to a degree or so, and a keyframe
placed on one such match passes that error on to the whole map. So a narrow scan's pose is the
information-weighted mean of the latest matches, each carried to the current scan by odometry
and counting less the farther it was carried (``matcher.narrow_smoothing``). The matches are
kept relative to the keyframe they were made after, so they follow it when a loop closure or
a merge moves the graph.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, pose_distance, wrap_angle
from server.slam.config import GraphConfig
from server.slam.frontend import FrontendMatch, MatchKind
from server.slam.measurements import rotation_xyt

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class KeptMatch:
    """One match: its anchor keyframe's graph key, the pose relative to that keyframe, the
    match's information in the robot frame, and the odometry pose at the scan."""

    anchor_key: int
    T_anchor_robot: F64
    information_robot: F64
    T_odom_robot: F64


@dataclass
class RecentMatches:
    """The latest ``keep`` matches of one robot's narrow scans (see the module)."""

    keep: int
    matches: list[KeptMatch] = field(default_factory=list)

    def clear(self) -> None:
        """Forget every match (a whole scan outweighs the views before it)."""
        self.matches.clear()

    def smoothed(self, match: FrontendMatch, T_odom_robot: F64, anchor_key: int,
                 T_map_anchor: F64, pose_of_key: Callable[[int], F64],
                 odometry: GraphConfig) -> FrontendMatch:
        """Keep ``match`` (if ICP found it) and return its pose averaged with the kept ones:
        x̂ = x₀ + (Σ Hᵢ)⁻¹ Σ Hᵢ (xᵢ − x₀), where xᵢ is match i carried here by odometry and
        Hᵢ = (Σᵢ + Σ_odom(carried))⁻¹ its information. ``match`` itself when it is odometry's
        or the only one kept."""
        if match.kind in (MatchKind.ICP, MatchKind.DEGENERATE):
            T = match.T_map_robot
            R = rotation_xyt(T[2])
            self.matches.append(KeptMatch(anchor_key, between(T_map_anchor, T),
                                          R.T @ match.information @ R, T_odom_robot))
        del self.matches[:-self.keep]
        if match.kind == MatchKind.ODOMETRY or len(self.matches) < 2:
            return match
        T0 = match.T_map_robot
        H, b = np.zeros((3, 3)), np.zeros(3)
        for kept in self.matches:
            T_j = compose(pose_of_key(kept.anchor_key), kept.T_anchor_robot)
            R = rotation_xyt(T_j[2])
            carried = between(kept.T_odom_robot, T_odom_robot)
            d, a = pose_distance(carried)
            s_xy = odometry.odometry_sigma_m_per_m * d + 1e-3
            s_th = math.radians(odometry.odometry_sigma_deg_per_rad * a) + 1e-4
            cov = np.linalg.inv(R @ kept.information_robot @ R.T + 1e-6 * np.eye(3))  # unseen
            info = np.linalg.inv(cov + np.diag([s_xy ** 2, s_xy ** 2, s_th ** 2]))
            T = compose(T_j, carried)
            e = np.array([T[0] - T0[0], T[1] - T0[1], wrap_angle(T[2] - T0[2])])
            H += info
            b += info @ e
        if not H.any():
            return match
        delta = np.linalg.solve(H + 1e-9 * np.eye(3), b)
        T = T0 + delta
        T[2] = wrap_angle(T[2])
        return FrontendMatch(T, match.kind, match.information, match.inlier_fraction)
