"""A transform between two teams' maps checked against what their robots see now.

Under a transform that is right, every robot of the other team stands where the transform
puts it in this team's frame. A robot of this team whose latest scan looks at that spot and
finds open floor there, its beams passing through and beyond, has seen that the transform is
wrong: nobody stands there. A floor of offices alike fits two maps under several transforms
(`docs/detours.md`); the robots' own eyes tell them apart without driving anywhere.

The spot is a disc (``RADIUS_M``): the other robot's body, its pose error, and a transform
only roughly right, as a meeting's may be (one 0.74 m off still brought two robots together
in the large house, and their tags merged them). It is seen empty when every beam toward it
ends beyond it, with ``MIN_BEAMS`` beams or more on it, from at most ``RANGE_M`` away
(farther, the beams thin out); a wall in it, or a beam not read (NaN), tells nothing, and
neither does a beam with no return from a sensor whose range ends before the disc's far side
(a depth camera's 3 m). One look can be unlucky (a pose off for a moment), so a transform is
taken as contradicted after ``LOOKS`` looks at least ``LOOKS_SPAN_S`` apart in all. No I/O
here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import inverse, transform_points
from server.fleet.model import LiveView

if TYPE_CHECKING:
    from server.fleet.model import Fleet, RobotContext

F64 = NDArray[np.float64]

#: the disc where the other robot must stand under the transform [m]
RADIUS_M = 1.0
#: a look from farther than this tells nothing [m]
RANGE_M = 8.0
#: beams a look needs on the disc
MIN_BEAMS = 5
#: a look and the other robot's pose at most this far apart in time [s]
SAME_TIME_S = 0.25
#: looks that contradict a transform before it is taken as wrong, and how long they span [s]
LOOKS, LOOKS_SPAN_S = 3, 1.0


def seen_empty(view: LiveView, q: F64, radius: float = RADIUS_M) -> bool:
    """Whether ``view`` saw the disc of ``radius`` around ``q`` (its team's frame) empty."""
    rel = transform_points(inverse(view.pose), np.asarray(q, np.float64).reshape(1, 2))[0]
    d = float(math.hypot(rel[0], rel[1]))
    if d > RANGE_M or d <= radius + 0.2:
        return False
    bearing, half = math.atan2(rel[1], rel[0]), math.asin(radius / d)
    off = np.abs((view.angles - bearing + math.pi) % (2 * math.pi) - math.pi)
    on = off <= half
    r = view.ranges[on]
    if len(r) < MIN_BEAMS or np.isnan(r).any():
        return False            # too few beams, or some unread: cannot tell
    if np.isinf(r).any() and not view.range_max_m > d + radius:
        return False            # no return within a range short of the disc's far side
    return bool(np.all(r > d + radius))      # (+inf: no return within the sensor's range)


@dataclass
class Contradictions:
    """Looks that found open floor where a transform puts a robot: per entry, their stamps."""

    looks: dict[int, list[int]] = field(default_factory=dict)

    def check(self, fleet: Fleet, key: int, team_a: str, team_b: str, T_ab: F64
              ) -> str | None:
        """One round of looks for the transform ``T_ab`` (``team_b``'s frame into
        ``team_a``'s); the reason it is wrong once ``LOOKS`` looks found open floor."""
        for own, other, T in ((team_a, team_b, T_ab), (team_b, team_a, inverse(T_ab))):
            found = _look(fleet, own, other, T)
            if found is None:
                continue
            seer, seen, stamp = found
            stamps = self.looks.setdefault(key, [])
            if stamp not in stamps:
                stamps.append(stamp)
            if len(stamps) >= LOOKS and stamps[-1] - stamps[0] >= LOOKS_SPAN_S * 1e9:
                return (f"{seer} looked where the maps put {seen} and saw open floor "
                        f"({len(stamps)} times in {(stamps[-1] - stamps[0]) * 1e-9:.1f} s)")
        return None

    def forget(self, key: int) -> None:
        self.looks.pop(key, None)


def _look(fleet: Fleet, own: str, other: str, T: F64) -> tuple[str, str, int] | None:
    """A robot of team ``own`` whose latest scan saw open floor where ``T`` puts a robot of
    team ``other``: (it, that robot, the scan's stamp)."""
    mine = [fleet.robots[r] for r in fleet.teams[own].robot_ids]
    theirs = [fleet.robots[r] for r in fleet.teams[other].robot_ids]
    for b in theirs:
        if not _live(b):
            continue
        q = transform_points(T, b.pose[None, :2])[0]
        for a in mine:
            v = a.view
            if not _live(a) or v is None or v.team_id != own or \
                    abs(v.stamp_ns - b.last_stamp_ns) > SAME_TIME_S * 1e9:
                continue
            if seen_empty(v, q):
                return a.robot_id, b.robot_id, v.stamp_ns
    return None


def _live(r: RobotContext) -> bool:
    return r.alive and not r.ghost and r.scans > 0
