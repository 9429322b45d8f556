"""Typed planning failures; callers (the explorer, the daemon) decide what to do about each."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


class PlanningError(Exception):
    """A path could not be planned; the subclass says why."""


class OutsideGrid(PlanningError):
    """The start or the goal lies outside the grid."""


class StartOccupied(PlanningError):
    """The start cell is lethal and no traversable cell lies within the escape radius."""


class GoalOccupied(PlanningError):
    """The goal cell is lethal (an obstacle, or closer to one than the robot radius)."""


class NoPath(PlanningError):
    """Start and goal are traversable but not connected through traversable cells."""


class PlanningTimedOut(PlanningError):
    """The search ran past its time budget."""


def describe_xy(xy: ArrayLike) -> str:
    """``(x, y)`` with millimetre precision, for error messages."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1)
    return f"({p[0]:.3f}, {p[1]:.3f})"
