"""Targets for a team: the robots of a merged team decide together.

``TeamExplorer`` stands in for a robot's explorer once its team has more than one robot. When
that robot needs a target, teammates still heading for an open target keep it (their goals are
reserved), unless a robot being assigned would get there in less than half the path the
teammate still has to drive: then it may be assigned that goal, and the teammate chooses again
(a robot does not cross the building to a frontier a teammate stands beside). The robot and
every teammate without a target are assigned jointly:

- ``joint``: the free robots are assigned together: the minimum total path cost over the
  team's cost matrix (Hungarian method), then, where two targets lie within the reserve radius,
  the robot whose giving way costs the team less moves on (``assign_spread``: a heuristic,
  not an optimum of the whole problem); a robot
  whose sensor sees less far than a target's nearest mapped wall pays for the difference
  (``walls_beyond_reach``), so open space goes to the long-range robots;
- ``greedy``: the dissertation's rule — the robot takes its cheapest target at least the
  reserve radius (2 m) from the others' goals.

Teammates that received a target this way are redirected at once. A robot left without a
target of its own goes where a teammate goes rather than stand idle: the space behind one
frontier can be a whole room, and the team is not done until its coverage is reached.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from schemas.occupancy import OCCUPIED_ABOVE
from server.exploration import (
    Decision,
    Explorer,
    ExplorerParams,
    Finished,
    TeamCosts,
    VisitedTargets,
    assign_spread,
)
from server.exploration.navigator import Navigator, NavMode
from server.planning import OccupancyGrid, polyline_length_m

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class Member:
    robot_id: str
    pose: F64
    start_pose: F64
    nav: Navigator
    #: how far its range sensor sees (a depth camera's few metres, a LIDAR's ten or more)
    sensor_range_m: float = math.inf


def walls_beyond_reach(grid: OccupancyGrid, targets_xy: F64, ranges_m: Sequence[float],
                       weight: float) -> F64:
    """Extra cost (R, K) for each robot at each target: ``weight`` × how much farther the
    nearest mapped wall is from the target than the robot's sensor reaches, beyond what the
    team's longest-range sensor misses there too. A robot that sees a few metres must drive
    through open space to map it, where a long-range one sweeps it in passing; in rooms and
    corridors (walls within reach of both), and in a team of like sensors, nothing changes."""
    out = np.zeros((len(ranges_m), len(targets_xy)))
    r = np.minimum(np.asarray(ranges_m, dtype=np.float64), 1e3)
    if not len(targets_xy) or weight <= 0 or np.ptp(r) == 0:
        return out
    rows, cols = np.nonzero(grid.data > OCCUPIED_ABOVE)
    if len(rows) == 0:
        return out
    res = grid.resolution_m
    walls = np.column_stack([grid.origin_xy[0] + (cols + 0.5) * res,
                             grid.origin_xy[1] + (rows + 0.5) * res])
    d, _ = cKDTree(walls).query(targets_xy)
    return weight * (np.maximum(0.0, d[None, :] - r[:, None]) - np.maximum(0.0, d - r.max()))


def in_sight(grid: OccupancyGrid, targets_xy: F64, reach_m: float) -> NDArray[np.bool_]:
    """(K, K): the pairs of targets within ``reach_m`` of each other with no mapped wall on
    the straight line between them (a mapped wall's cells block it; targets stand a robot's
    radius from walls, and a line along a wall grazes it)."""
    k = len(targets_xy)
    out = np.zeros((k, k), dtype=bool)
    if k < 2 or not math.isfinite(reach_m) or reach_m <= 0:
        return out
    xy = np.asarray(targets_xy, np.float64)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    ii, jj = np.nonzero(np.triu(d < reach_m, 1))
    if not len(ii):
        return out
    blocked = grid.occupied
    res = grid.resolution_m
    h, w = blocked.shape
    n = math.ceil(reach_m / res * 2) + 2
    t = np.linspace(0.0, 1.0, n)
    px = xy[ii, None, 0] + t[None, :] * (xy[jj, None, 0] - xy[ii, None, 0])
    py = xy[ii, None, 1] + t[None, :] * (xy[jj, None, 1] - xy[ii, None, 1])
    cols = np.floor((px - grid.origin_xy[0]) / res).astype(np.int64)
    rows = np.floor((py - grid.origin_xy[1]) / res).astype(np.int64)
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    hit = np.where(inside, blocked[rows.clip(0, h - 1), cols.clip(0, w - 1)], False)
    clear = ~hit.any(axis=1)
    out[ii[clear], jj[clear]] = True
    return out | out.T


# A teammate's goal is taken over by a robot whose path to it is shorter than this share of
# the path the teammate still has to drive there.
TAKE_OVER_SHARE = 0.5


def remaining_m(path_xy: F64 | None, pose: ArrayLike) -> float:
    """Length [m] from ``pose`` to the path's nearest point and on along it to its end (∞
    without a path)."""
    if path_xy is None or len(path_xy) == 0:
        return math.inf
    xy = np.asarray(path_xy, np.float64).reshape(-1, 2)
    at = np.asarray(pose, np.float64).reshape(-1)[:2]
    if len(xy) == 1:
        return float(np.hypot(*(xy[0] - at)))
    a, b = xy[:-1], xy[1:]
    ab = b - a
    t = np.clip(np.sum((at - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-12),
                0.0, 1.0)
    foot = a + t[:, None] * ab
    i = int(np.argmin(np.hypot(*(foot - at).T)))
    return (float(np.hypot(*(foot[i] - at))) + float(np.hypot(*(b[i] - foot[i])))
            + polyline_length_m(xy[i + 1:]))


class TeamExplorer:
    """The explorer of one robot in a team of several (same ``decide`` as ``Explorer``)."""

    def __init__(self, base: Explorer, robot_id: str, members: Callable[[], Sequence[Member]],
                 mode: str = "joint", sensor_weight: float = 2.0,
                 sight_spread: bool = True) -> None:
        if mode not in ("joint", "greedy"):
            raise ValueError(f"unknown coordination {mode!r}")
        self.base = base
        self.robot_id = robot_id
        self.members = members
        self.mode = mode
        self.sensor_weight = sensor_weight
        self.sight_spread = sight_spread
        self.assignments = 0
        #: goals taken from a teammate by a robot that gets there in far less (``_hold``)
        self.takeovers = 0

    @property
    def params(self) -> ExplorerParams:
        return self.base.params

    def __getattr__(self, name: str) -> object:
        # everything but the decision is the robot's own explorer's (map analysis, ...);
        # not while unpickling, before ``base`` is there
        if name.startswith("__") or "base" not in self.__dict__:
            raise AttributeError(name)
        return getattr(self.base, name)

    def decide(self, grid: OccupancyGrid, robot_pose: ArrayLike, start_pose: ArrayLike,
               visited: VisitedTargets, reserved_xy: ArrayLike = ()) -> Decision | Finished:
        team = list(self.members())
        me = next((i for i, m in enumerate(team) if m.robot_id == self.robot_id), None)
        if me is None or len(team) < 2:
            return self.base.decide(grid, robot_pose, start_pose, visited, reserved_xy=reserved_xy)
        others = [m for m in team if m.robot_id != self.robot_id]
        committed = np.array([m.nav.target_xy for m in others if m.nav.target_xy is not None],
                             dtype=np.float64).reshape(-1, 2)
        if self.mode == "greedy":
            return self._alone(grid, robot_pose, start_pose, visited, committed)
        free = [i for i, m in enumerate(team)
                if i == me or (m.nav.target_xy is None and m.nav.mode != NavMode.DONE)]
        tc = self.base.team_costs(grid, [team[i].pose for i in free],
                                  [team[i].start_pose for i in free], visited)
        if tc.cost.shape[1] == 0:
            return self._alone(grid, robot_pose, start_pose, visited, committed)
        extra = walls_beyond_reach(grid, tc.targets_xy, [team[i].sensor_range_m for i in free],
                                   self.sensor_weight)
        cost = tc.cost + extra
        held = self._hold(team, free, tc, extra, cost)
        assignment = assign_spread(cost, tc.targets_xy, self.params.reserve_radius_m,
                                   self._sight_clashes(grid, tc.targets_xy,
                                                       [team[i].sensor_range_m for i in free]))
        mine = assignment[free.index(me)]
        if mine is None:
            return self._alone(grid, robot_pose, start_pose, visited, committed)
        self.assignments += 1
        self._take_over(team, free, assignment, held)
        for row, i in enumerate(free):
            k = assignment[row]
            if i == me or k is None:
                continue
            try:
                path = tc.path(row, k)
            except Exception as e:  # a teammate that cannot be planned for decides alone
                log.info("no path for %s to its assigned target: %s", team[i].robot_id, e)
                continue
            xy = (float(tc.targets_xy[k, 0]), float(tc.targets_xy[k, 1]))
            team[i].nav.redirect(xy, path.xy_m)
        xy = (float(tc.targets_xy[mine, 0]), float(tc.targets_xy[mine, 1]))
        return Decision(xy, tc.path(free.index(me), mine), f"team assignment ({tc.kind})",
                        (), None)

    def _hold(self, team: Sequence[Member], free: list[int], tc: TeamCosts, extra: F64,
              cost: F64) -> list[tuple[int, NDArray[np.bool_], float]]:
        """Keep the free robots (rows of ``cost``, set to ∞ in place) off the targets near a
        teammate's goal, unless one of them would get there in less than ``TAKE_OVER_SHARE``
        of the path the teammate still has to drive: a goal is held for the robot that gets
        there first, not for the one that chose it first. Returns, per teammate with a goal,
        (its index, the targets near its goal, its remaining path [m])."""
        r = self.params.reserve_radius_m
        held: list[tuple[int, NDArray[np.bool_], float]] = []
        for j, m in enumerate(team):
            if j in free or m.nav.target_xy is None or m.nav.mode == NavMode.DONE:
                continue
            goal = np.asarray(m.nav.target_xy, np.float64)
            near = np.hypot(*(tc.targets_xy - goal).T) < r
            if not near.any():
                continue
            left = remaining_m(m.nav.path_xy, m.pose)
            for row in range(len(free)):
                f = tc.fields[row]
                for k in np.flatnonzero(near & np.isfinite(cost[row])):
                    d = (math.inf if f is None or not math.isfinite(left)
                         else f.length_m(tc.targets_xy[k]) + float(extra[row, k]))
                    if d >= TAKE_OVER_SHARE * left:
                        cost[row, k] = np.inf
            held.append((j, near, left))
        return held

    def _take_over(self, team: Sequence[Member], free: list[int], assignment: list[int | None],
                   held: list[tuple[int, NDArray[np.bool_], float]]) -> None:
        """A teammate whose goal a free robot was assigned (see ``_hold``) chooses again."""
        for j, near, left in held:
            taker = next((free[row] for row, k in enumerate(assignment)
                          if k is not None and near[k]), None)
            if taker is None:
                continue
            nav = team[j].nav
            log.info("%s takes over %s's goal %s: %.1f m of %s's path were left",
                     team[taker].robot_id, team[j].robot_id,
                     tuple(round(v, 2) for v in nav.target_xy or ()), left, team[j].robot_id)
            nav.drop_target()
            self.takeovers += 1

    def _sight_clashes(self, grid: OccupancyGrid, targets_xy: F64,
                       ranges_m: Sequence[float]) -> NDArray[np.bool_] | None:
        """In a team of unlike sensors, two targets in sight of each other within the longest
        sensor's reach clash: a long-range robot at either maps what lies behind the other
        too, so a second robot sent there (the slow, short-sighted one beside it, or the
        fast one beside a room the slow one is mapping) adds nothing while other unexplored
        space waits. In a team of like sensors nothing changes (None)."""
        r = np.minimum(np.asarray(ranges_m, dtype=np.float64), 1e3)
        if not self.sight_spread or len(r) < 2 or np.ptp(r) == 0:
            return None
        return in_sight(grid, targets_xy, float(r.max()))

    def _alone(self, grid: OccupancyGrid, robot_pose: ArrayLike, start_pose: ArrayLike,
               visited: VisitedTargets, committed: F64) -> Decision | Finished:
        """The robot's own decision away from its teammates' goals, or next to one of them
        when that is all there is."""
        out = self.base.decide(grid, robot_pose, start_pose, visited, reserved_xy=committed)
        if isinstance(out, Finished) and len(committed) and not (
                out.coverage is not None and out.coverage >= self.params.coverage_threshold):
            out = self.base.decide(grid, robot_pose, start_pose, visited)
        return out
