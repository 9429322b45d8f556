"""Square walls' ties in the graph: heading-only factors between a robot's own keyframes where
the rule of ``server.slam.heading`` says what their relative heading is (``slam.square_walls``).

The rule itself (wall directions, whether a building's walls are square, which earlier
keyframes to tie to) is ``SquareWalls``; this part reads the keyframes' estimates, adds the
factors and sets the rule's reference from a whole scan taken at the start. One robot has one
``HeadingTies``, shared by its sensor models: with ``square_walls.narrow_only`` off, a 360°
scan's keyframes join the same set of walls as a narrow one's.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from factors.scan_match import heading_factor
from schemas.se2 import between, pose_distance, wrap_angle
from server.slam.backend import PoseGraph, RobotTrajectory, add_constraint
from server.slam.config import SquareWallsConfig
from server.slam.heading import SquareWalls, wall_direction, wrap_quarter

F64 = NDArray[np.float64]


class HeadingTies:
    """One robot's square walls and the ties they gave (see the module)."""

    def __init__(self, cfg: SquareWallsConfig) -> None:
        self.cfg = cfg
        self.walls = SquareWalls(cfg.min_points, cfg.min_alignment, cfg.agree_deg,
                                 cfg.max_correction_deg, cfg.min_checked, cfg.min_agreement,
                                 cfg.partners)

    @property
    def reference(self) -> tuple[int, float] | None:
        """The keyframe whose wall direction every tie includes, and that direction."""
        return self.walls.reference

    def tie(self, graph: PoseGraph, trajectory: RobotTrajectory, k: int, normals: F64,
            T_map_robot: F64) -> bool:
        """Tie keyframe ``k`` (at ``T_map_robot``, with ``normals`` in its own frame) in
        heading to the earlier keyframes its walls agree with. The ties' σ is
        ``sigma_deg``·√n over the n ties other than the reference's, so that they hold
        together as one; the reference's tie keeps its full ``sigma_deg``. Whether any was
        added."""
        c = self.cfg
        if not c.enabled:
            return False
        poses: dict[int, F64] = {}    # the earlier keyframes' estimates, each read once

        def relative_heading(j: int) -> float:
            poses[j] = graph.pose(trajectory.key(j))
            return float(wrap_angle(T_map_robot[2] - poses[j][2]))

        ties = self.walls.observe(k, normals, relative_heading)
        ref = self.walls.reference
        others = sum(ref is None or j != ref[0] for j, _ in ties)
        sigma_rad = math.radians(c.sigma_deg) * math.sqrt(max(others, 1))
        for j, heading in ties:
            T = between(poses[j], T_map_robot)
            T[2] = heading
            s = math.radians(c.sigma_deg) if ref is not None and j == ref[0] else sigma_rad
            add_constraint(graph, trajectory, heading_factor(
                trajectory.key(j), trajectory.key(k), T, s, c.huber_k), "heading")
        return bool(ties)

    def set_reference(self, normals: F64, T_odom_first: F64, T_odom_robot: F64,
                      still_m: float, still_deg: float) -> None:
        """A whole scan (``normals``, robot frame at ``T_odom_robot``) taken before the robot
        moved from its first keyframe (at ``T_odom_first``: within ``still_m`` and
        ``still_deg``) gives that keyframe's wall direction far better than any narrow view:
        every tie then includes keyframe 0 (``SquareWalls.reference``). Nothing otherwise,
        or when its walls are not square."""
        d, a = pose_distance(between(T_odom_first, T_odom_robot))
        if d > still_m or a > math.radians(still_deg):
            return
        found = wall_direction(normals, self.cfg.min_points)
        if found is None or found[1] < self.cfg.min_alignment:
            return
        turned = wrap_angle(T_odom_robot[2] - T_odom_first[2])
        self.walls.reference = (0, wrap_quarter(found[0] + turned))
