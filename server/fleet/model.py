"""The fleet: every robot the server tracks, the teams they form, the links and merges that
joined them, and each team's grid.

A robot gets its own graph symbols when it is first heard of (numbers are never reused, so a
robot that comes back under a new name cannot collide with an old graph) and starts in a team
of its own. The rendezvous merger moves robots between teams; everything else reads them.
No I/O here.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose, inverse, transform_points
from server.config import ServerConfig
from server.exploration import VisitedTargets
from server.exploration.navigator import Navigator
from server.fleet.coordination import Member, TeamExplorer
from server.fleet.detours import Detours
from server.fleet.events import EventLog
from server.fleet.stages import Stages
from server.lookout import Lookout
from server.planning import OccupancyGrid as PlanningGrid
from server.slam import RobotSlam
from server.slam.backend import FactorRecord, robot_key_space
from server.slam.grid import OccupancyGrid
from server.slam.keyframes import Keyframe
from server.slam.mapping import GridMapper
from server.slam.stamped import StampedRows

if TYPE_CHECKING:
    from server.control import ObstacleMemory

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class Meeting:
    """A meeting planned on a map-matched transform (``server.rendezvous.matchdesk``): the
    robot that goes drives to where the transform puts the other, which waits."""

    role: str                      # "go" or "wait"
    other: str                     # the robot of the other team
    hypothesis: int                # its index in the desk's log
    until_s: float                 # given up (and the transform refuted) after this
    target_xy: F64 | None = None   # where to go (team frame), for "go"
    path_xy: F64 | None = None     # planned on the team's map
    team_id: str = ""              # the robot's team when planned (whose frame these are in)
    arrived_ns: int = 0            # when it reached its place (0: not yet)


@dataclass
class LiveView:
    """A robot's latest scan as the server used it: when, in which team's frame, from where,
    and its beams (ranges [m], NaN for none, and bearings [rad], in the robot's frame)."""

    stamp_ns: int
    team_id: str
    pose: F64
    ranges: F64
    angles: F64
    range_max_m: float = float("inf")     # a no-return (+inf) says: nothing nearer


class Sighted(NamedTuple):
    """A tag sighting between a robot and one of another team, as the robot keeps it."""

    stamp_ns: int           # the robot's latest scan stamp when it was placed
    T_own_other: F64        # the other's team frame in the robot's team frame
    own_team: str           # the two teams then (a merge changes the frames)
    other_team: str


@dataclass
class RobotContext:
    robot_id: str
    slam: RobotSlam
    nav: Navigator
    team_id: str
    look: Lookout
    start_pose: F64 = field(default_factory=lambda: np.zeros(3))
    pose: F64 = field(default_factory=lambda: np.zeros(3))
    distance_m: float = 0.0
    scans: int = 0
    late_scans: int = 0          # answered with a stop: the server got to them too late
    last_stamp_ns: int = 0
    alive: bool = True
    start_checked: bool = False   # a known start pose was used (or there was none to use)
    #: the pose the server believed at each scan (stamps; values x, y, θ), in the robot's own
    #: map frame (its first pose is the origin; a merge does not move it)
    online: StampedRows = field(default_factory=lambda: StampedRows(3))
    #: the same poses while in a team, in the own map frame of the team's first robot (the
    #: frame its map is drawn in), keyed by that robot: where the team's map puts it
    online_in: dict[str, StampedRows] = field(default_factory=dict)
    meeting: Meeting | None = None
    #: its latest scan (``server.rendezvous.liveview``: transforms checked against it)
    view: LiveView | None = None
    sensor_range_m: float = float("inf")   # its latest scan's maximum range
    #: a narrow sensor's recent obstacles, for the reactive layer (``server.command.steering``)
    obstacles: ObstacleMemory | None = None
    #: robots of other teams it saw or was seen by lately, and where their team frames lie
    #: in its own then (robot id -> ``Sighted``)
    sighted: dict[str, Sighted] | None = None
    #: not a robot: keyframes its team's map is drawn from (a known map; a robot's graph
    #: from before it was lost: ``server.knownmap``); never reported, never driven
    ghost: bool = False
    #: its keyframes are not drawn into its team's map (a robot localising on a known map)
    unmapped: bool = False
    #: keyframes left out of its team's map (out of date, or made while lost)
    retired: set[int] = field(default_factory=set)

    def __getstate__(self) -> dict[str, object]:
        # its latest scan is the moment's, not state: the next scan after a restart gives it
        return {**self.__dict__, "view": None}

    def mapped_keyframes(self) -> tuple[list[Keyframe], F64]:
        """The keyframes its team's map is drawn from, and their poses."""
        sl = self.slam
        if self.unmapped:
            return [], np.zeros((0, 3))
        if not self.retired:
            return sl.keyframes, sl.keyframe_poses()
        keep = [k for k in range(len(sl.keyframes)) if k not in self.retired]
        return [sl.keyframes[k] for k in keep], sl.keyframe_poses()[keep].reshape(-1, 3)

    def own_frame_in_team(self) -> F64:
        """The robot's own map frame (its first pose) in its team's frame, exactly: the first
        keyframe's team pose against where the robot's prior put it."""
        sl = self.slam
        return compose(sl.keyframe_pose(0), inverse(sl.trajectory.prior_pose()))


@dataclass
class Link:
    """A factor between two robots' graphs inside a team's graph: a tag sighting
    (``rendezvous``), a map match (``cross``), known start poses (``start``) or a marker."""

    a: str
    b: str
    stamp_ns: int
    record: FactorRecord
    retired: bool = False    # out of the graph: map matches tie the pair (tag sightings only)


@dataclass
class MergeRecord:
    stamp_ns: int
    team_id: str                  # the team that absorbed the other
    joined_team_id: str
    robots_a: list[str]
    robots_b: list[str]
    sightings: list[tuple[str, str, int]]   # (observer, observed, stamp_ns)
    T_fused: F64                  # b's frame -> a's frame, fused sightings (direct method)
    cov_fused: F64
    T_direct_first: F64           # the direct method on the first sighting alone
    T_joint: F64                  # after the joint optimisation
    agreement: dict[str, float]
    undone_stamp_ns: int | None = None
    #: tags | start (known start poses) | marker (given by hand) | map (the maps alone) |
    #: meeting (tags, at a meeting planned on the maps) | placed (in a known map: by its
    #: map, or by hand)
    kind: str = "tags"


@dataclass
class Team:
    team_id: str
    robot_ids: list[str]
    visited: VisitedTargets
    coverage: float = 0.0
    explored_m2: float = 0.0
    finished: bool = False
    finished_stamp_ns: int | None = None
    history: list[tuple[int, float]] = field(default_factory=list)  # (stamp_ns, coverage)
    anchor: str = ""              # the robot whose first pose is the team frame's origin
    mapper: GridMapper | None = None
    links: list[Link] = field(default_factory=list)
    merged_into: str | None = None
    #: a known map's team (``server.knownmap``): robots join it by being placed in it, not
    #: by the map matching between teams
    known: bool = False


def _pair(team_a: str, team_b: str) -> tuple[str, str]:
    return (team_a, team_b) if team_a <= team_b else (team_b, team_a)


class Fleet:
    """Robots, teams, merges and team grids; one thread uses it."""

    def __init__(self, cfg: ServerConfig, stages: Stages, events: EventLog) -> None:
        self.cfg, self.stages, self.events = cfg, stages, events
        self.robots: dict[str, RobotContext] = {}
        self.teams: dict[str, Team] = {}
        self.retired_teams: dict[str, Team] = {}   # merged into another (until undone)
        self.merges: list[MergeRecord] = []
        #: each team's planning grid as of the last coverage update (``server.fleet.progress``)
        self.latest_grids: dict[str, PlanningGrid] = {}
        #: refused merges of two teams (ids in order): the current run of refusals, none
        #: more than ``teams.refusal_pause_s`` after the one before (latest, how many)
        self.refusals: dict[tuple[str, str], tuple[int, int]] = {}
        #: every detour priced, taken or declined, and its outcome (``server.fleet.detours``)
        self.detours = Detours(cfg, self, events)
        self._robots_added = 0   # robot numbers are never reused: each owns its graph keys
        #: a worker of a split server numbers its robots n·64 + its worker number, so that
        #: graphs moved between workers never share keys
        w = cfg.cluster.worker
        self._key_stride, self._key_offset = (1, 0) if w is None else (64, w)

    # -- refused merges --------------------------------------------------------------------
    def refused(self, team_a: str, team_b: str, stamp_ns: int) -> None:
        """The maps refused a merge of two teams (see ``seeking_paused``)."""
        key = _pair(team_a, team_b)
        last, count = self.refusals.get(key, (stamp_ns, 0))
        if stamp_ns - last > self.cfg.teams.refusal_pause_s * 1e9:
            count = 0
        self.refusals[key] = (max(last, stamp_ns), count + 1)
        # pairs of teams that are gone (merged) are forgotten
        self.refusals = {k: v for k, v in self.refusals.items()
                         if k[0] in self.teams and k[1] in self.teams}

    def seeking_paused(self, team_a: str, team_b: str, now_ns: int) -> bool:
        """Two teams whose merge the maps have kept refusing: ``teams.refusals_to_pause``
        refusals or more, none ``teams.refusal_pause_s`` after the one before, the latest
        within that time. Their robots do not seek each other out (calls, approaches,
        meetings): robots that read each other's tags but whose maps disagree would
        otherwise follow each other instead of exploring. A team that has finished
        exploring has nothing better to do, and seeks on."""
        t = self.cfg.teams
        run = self.refusals.get(_pair(team_a, team_b))
        if run is None or t.refusals_to_pause <= 0:
            return False
        if any(tid in self.teams and self.teams[tid].finished for tid in (team_a, team_b)):
            return False
        last, count = run
        # (a clock stepped back before the latest refusal: seek, rather than wait for it)
        return count >= t.refusals_to_pause and 0 <= now_ns - last < t.refusal_pause_s * 1e9

    def others_paused(self, r: RobotContext, now_ns: int) -> bool:
        """Every team but ``r``'s is one it does not seek out now (see ``seeking_paused``)."""
        if r.meeting is not None:
            return False        # a meeting planned before the refusals: it goes on
        others = [tid for tid in self.teams if tid != r.team_id]
        return bool(others) and all(self.seeking_paused(r.team_id, tid, now_ns)
                                    for tid in others)

    # -- robots ----------------------------------------------------------------------------
    def add_robot(self, robot_id: str) -> RobotContext:
        """A robot heard of for the first time: its own graph symbols, navigator, lookout and
        a team of its own."""
        char, block = self.key_space()
        nav = self.stages.navigator()
        team_id = f"team-{robot_id}"
        r = RobotContext(robot_id, self.stages.slam(char, block), nav, team_id,
                         self.stages.lookout(robot_id))
        self.robots[robot_id] = r
        self.teams[team_id] = Team(team_id, [robot_id], self.stages.visited(),
                                   anchor=robot_id, mapper=self.stages.mapper())
        self.events.emit("robot_joined", [robot_id], team_id, f"robot {robot_id} joined", 0)
        log.debug("robot %s tracked as graph symbol %r (block %d) in %s", robot_id, char,
                  block, team_id)
        return r

    def key_space(self) -> tuple[str, int]:
        """The graph symbol and key block of the next graph (a robot's, or a known map's)."""
        char, block = robot_key_space(self._robots_added * self._key_stride + self._key_offset)
        self._robots_added += 1
        return char, block

    def set_alive(self, robot_id: str, alive: bool) -> None:
        r = self.robots.get(robot_id)
        if r is not None and r.alive != alive:
            r.alive = alive
            self.events.emit("robot_joined" if alive else "robot_lost", [robot_id], r.team_id,
                             f"robot {robot_id} {'is back' if alive else 'vanished'}",
                             r.last_stamp_ns)

    def team_of(self, r: RobotContext) -> Team:
        return self.teams[r.team_id]

    def mates_xy(self, r: RobotContext, alive_only: bool = True) -> F64:
        """Where ``r``'s teammates are (N, 2), in the team frame."""
        xy = [self.robots[o].pose[:2] for o in self.teams[r.team_id].robot_ids
              if o != r.robot_id and not self.robots[o].ghost
              and (self.robots[o].alive or not alive_only)]
        return np.array(xy, dtype=np.float64).reshape(-1, 2)

    def without_teammates(self, r: RobotContext, ranges: F64, angles: F64) -> F64:
        """The scan for SLAM, without the beams that hit a teammate's body (as none): robots
        driving in a row along a corridor see each other where the walls say nothing along
        it, and a matcher that holds on to the robot ahead thinks it stands still."""
        team = self.teams.get(r.team_id)
        if team is None or len(team.robot_ids) < 2 or not r.scans:
            return ranges
        mates = np.array([self.robots[o].pose[:2] for o in team.robot_ids
                          if o != r.robot_id and self.robots[o].alive and self.robots[o].scans],
                         dtype=np.float64).reshape(-1, 2)
        if not len(mates):
            return ranges
        ok = np.isfinite(ranges) & np.isfinite(angles)
        idx = np.flatnonzero(ok)
        pts = np.stack([ranges[idx] * np.cos(angles[idx]), ranges[idx] * np.sin(angles[idx])], 1)
        world = transform_points(r.pose, pts)
        d = np.hypot(world[:, None, 0] - mates[None, :, 0],
                     world[:, None, 1] - mates[None, :, 1]).min(axis=1)
        hit = idx[d <= self.cfg.control.robot_radius_m + 0.15]
        if not len(hit):
            return ranges
        out = np.array(ranges, dtype=np.float64, copy=True)
        out[hit] = np.nan
        return out

    def mates_in_robot_frame(self, r: RobotContext) -> F64:
        """Live teammates' positions in ``r``'s body frame (for collision avoidance)."""
        xy = self.mates_xy(r)
        if not len(xy):
            return np.zeros((0, 2))
        return transform_points(inverse(r.pose), xy)

    def others_in_robot_frame(self, r: RobotContext) -> F64:
        """Robots ``r`` keeps clear of, in its body frame: its live teammates, and — if its
        latest scan was narrow (a camera on a tower, looking elsewhere, does not see a robot
        beside it; a LIDAR does) — live robots of other teams it saw or was seen by within
        ``control.sighted_robot_s``, placed by their own poses through that sighting."""
        mates = self.mates_in_robot_frame(r)
        keep_ns = self.cfg.control.sighted_robot_s * 1e9
        if not r.sighted or keep_ns <= 0 or not r.slam.narrow:
            return mates
        now = r.last_stamp_ns
        seen = []
        for rid, s in r.sighted.items():
            o = self.robots.get(rid)
            if o is None or not o.alive or not 0 <= now - s.stamp_ns <= keep_ns or \
                    r.team_id != s.own_team or o.team_id != s.other_team:
                continue   # stale, or a merge has changed the frames since
            seen.append(transform_points(s.T_own_other, o.pose[None, :2])[0])
        if not seen:
            return mates
        return np.vstack([mates, transform_points(inverse(r.pose), np.array(seen))])

    # -- teams -----------------------------------------------------------------------------
    def team_grid(self, team_id: str) -> OccupancyGrid:
        """The team's log-odds grid from all its robots' keyframes, in the team frame."""
        team = self.teams[team_id]
        assert team.mapper is not None
        return team.mapper.update_many({rid: self.robots[rid].mapped_keyframes()
                                        for rid in team.robot_ids})

    def planning_grid(self, team_id: str) -> PlanningGrid:
        """The team's occupancy grid in the nav2 convention (robots of one team share it)."""
        grid = self.team_grid(team_id)
        return PlanningGrid(grid.to_nav2(), grid.resolution_m,
                            (float(grid.origin[0]), float(grid.origin[1])))

    def coordinate(self, team: Team) -> None:
        """Robots of a team of several decide together (see ``server.fleet.coordination``)."""
        for rid in team.robot_ids:
            nav = self.robots[rid].nav
            if len(team.robot_ids) > 1:
                team_explorer = TeamExplorer(
                    nav.own_explorer, rid, functools.partial(self.members, team.team_id),
                    self.cfg.teams.coordination, self.cfg.teams.sensor_weight,
                    self.cfg.teams.sight_spread)
                nav.use_explorer(team_explorer)  # type: ignore[arg-type]
            else:
                nav.use_explorer(nav.own_explorer)

    def members(self, team_id: str) -> list[Member]:
        """The team's live robots, for its coordination."""
        team = self.teams.get(team_id)
        if team is None:
            return []
        return [Member(rid, self.robots[rid].pose, self.robots[rid].start_pose,
                       self.robots[rid].nav, self.robots[rid].sensor_range_m)
                for rid in team.robot_ids if self.robots[rid].alive]

    @property
    def finished(self) -> bool:
        """Every team with a live robot has finished (and there is one). A team whose robots
        all vanished cannot go on, so it does not hold the others' end back."""
        live = [t for t in self.teams.values()
                if any(self.robots[rid].alive for rid in t.robot_ids)]
        return bool(live) and all(t.finished for t in live)
