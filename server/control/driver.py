"""The one place a robot's twist is made: follow a path, keep clear of obstacles, clip.

Every behaviour that moves a robot (exploring, an operator's errand, a planned meeting, the
lookout's approach, recovery) proposes a path to follow or a twist of its own; the driver turns
it into the command: pure pursuit along the path, then VFH against one set of obstacles — the
scan's points and the robots the robot keeps clear of — then the limits. So no behaviour can
forget the robots a narrow sensor saw, or the limits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from server.control.geometry import Twist
from server.control.pure_pursuit import PurePursuit
from server.control.vfh import Vfh

F64 = NDArray[np.float64]

#: no command leaves the server faster than this, whatever a behaviour asked [m/s], [rad/s]
MAX_V_MPS = 5.0
MAX_OMEGA_RPS = 20.0


def _none() -> F64:
    return np.zeros((0, 2))


@dataclass(frozen=True)
class Obstacles:
    """What a robot keeps clear of, in its body frame [m]: points (its scan, and what a
    narrow sensor remembers or its team mapped nearby) and other robots' positions."""

    points_xy: F64 = field(default_factory=_none)
    robots_xy: F64 = field(default_factory=_none)


@dataclass(frozen=True)
class Drive:
    """A path followed one step: the twist, and whether the path's end is reached (then the
    twist is zero: the behaviour says what comes next)."""

    twist: Twist
    reached: bool


class Driver:
    def __init__(self, vfh: Vfh | None) -> None:
        self.vfh = vfh

    def follow(self, pursuit: PurePursuit, pose: F64, path_xy: F64, obstacles: Obstacles
               ) -> Drive:
        """One step along ``path_xy`` (world frame) by ``pursuit`` (the behaviour's own: it
        remembers its progress along its path), clear of ``obstacles``."""
        step = pursuit.step(pose, path_xy)
        if step.reached:
            return Drive(Twist(0.0, 0.0), True)
        return Drive(limit(self._clear(step.twist, step.heading_error_rad, obstacles)), False)

    def avoid(self, twist: Twist, heading_error_rad: float, obstacles: Obstacles) -> Twist:
        """A behaviour's own twist toward ``heading_error_rad`` (robot frame), clear of
        ``obstacles`` and within the limits. One that does not drive forward is only clipped:
        turning on the spot toward something runs into nothing."""
        if twist.v_mps > 0:
            twist = self._clear(twist, heading_error_rad, obstacles)
        return limit(twist)

    def _clear(self, twist: Twist, heading_error_rad: float, obstacles: Obstacles) -> Twist:
        if self.vfh is None:
            return twist
        return self.vfh.adjust(twist, heading_error_rad, obstacles.points_xy,
                               obstacles.robots_xy)


def limit(twist: Twist) -> Twist:
    """``twist`` within the limits every command keeps."""
    # min(max()) in this order is np.clip's, NaN included
    return Twist(min(max(float(twist.v_mps), -MAX_V_MPS), MAX_V_MPS),
                 min(max(float(twist.omega_rps), -MAX_OMEGA_RPS), MAX_OMEGA_RPS))
