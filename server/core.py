"""The server's orchestrator, free of I/O: scans and tag sightings in, velocity commands and
map/state messages out.

One call per scan does the robot's whole loop (see ``ServerCore.on_scan``):

    pose  = slam.add_scan(...)            # predict → match → keyframe → optimise → loop closure
    desk.process(...)                     # sightings whose scans are in → merges
    matcher.tick(...)                     # one pair of teams' maps matched → merges, meetings
    progress.tick(...)                    # coverage, termination, λ
    cmd   = steering.command(...)         # the operator's orders, the lookout, or
                                          # explore → plan → pursue → avoid

Stamps reach the core in the server's time (``server.runtime.node`` maps each robot's clock
onto it).
Periodic work (coverage and termination, map and state messages) runs on the ``now_ns`` the
caller passes: the server's own clock (the simulator's in lockstep, so a lockstep simulation
gives the same run every time); offline callers pass none and it runs on the scans' stamps.

The parts, each with one job: ``Fleet`` (robots, teams, merges, team grids), ``Stages``
(each robot's navigator, lookout and SLAM from the configuration), ``SightingDesk`` →
``Merger`` → ``GraphSurgery`` (rendezvous, in that direction), ``Progress`` and ``Steering``,
and the ``EventLog``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import Executor
from functools import partial

import msgspec
import numpy as np
from numpy.typing import NDArray

from schemas import (
    Event,
    MapUpdate,
    RobotEstimate,
    RobotStates,
    Scan,
    TagDetections,
    TeamCoverage,
    VelocityCommand,
)
from schemas.se2 import compose, inverse
from server.command.operator import OperatorCommand, OperatorError, OperatorOrders
from server.command.steering import Steering
from server.config import ServerConfig
from server.fleet.events import EventLog
from server.fleet.model import Fleet, LiveView, MergeRecord, RobotContext, Team
from server.fleet.progress import Progress
from server.fleet.stages import Stages
from server.knownmap.byhand import localisation, place_by_hand
from server.knownmap.desk import KnownMapDesk
from server.knownmap.ghosts import MAP_TEAM
from server.knownmap.mapdata import KnownMap
from server.planning import OccupancyGrid as PlanningGrid
from server.rendezvous.counters import RendezvousCounters
from server.rendezvous.desk import SightingDesk
from server.rendezvous.matchdesk import MapMatchDesk
from server.rendezvous.merger import Merger
from server.rendezvous.surgery import GraphSurgery
from server.slam.stamped import StampedRows

F64 = NDArray[np.float64]

#: a place on the pass over a known map not reached within this long is given up [s], and so
#: is one the robot has come no nearer to (along its path) by ``INSPECT_STALL_M`` for
#: ``INSPECT_STALL_S`` (a box or a closed door on the way)
INSPECT_GIVE_UP_S = 30.0
INSPECT_STALL_S, INSPECT_STALL_M = 8.0, 0.3


class ServerCore:
    """Per-robot SLAM and navigation, teams and their merges; one thread calls it."""

    def __init__(self, cfg: ServerConfig, navigate: bool = True,
                 known: KnownMap | None = None) -> None:
        self.cfg = cfg
        #: False: scans only feed SLAM, rendezvous and coverage (offline merging); commands are 0
        self.navigate = navigate
        self.events = EventLog()
        self.stages = Stages(cfg)
        self.fleet = Fleet(cfg, self.stages, self.events)
        self.counters = RendezvousCounters()
        self.surgery = GraphSurgery(cfg, self.fleet, self.counters)
        self.merger = Merger(cfg, self.fleet, self.stages, self.surgery, self.events,
                             self.counters)
        self.desk = SightingDesk(cfg, self.fleet, self.merger, self.counters,
                                 self.stages.pose_sigmas)
        self.matcher = MapMatchDesk(cfg, self.fleet, self.merger, self.events, self.counters)
        self.progress = Progress(cfg, self.fleet, self.events)
        #: what the operator ordered (``server.command.operator``): it wins over every other command
        self.orders = OperatorOrders()
        self.steering = Steering(cfg, self.fleet, self.orders, self.events)
        #: each robot's pose σ (x, y, θ) at its newest keyframe: (keyframes, σ)
        self._sigmas: dict[str, tuple[int, tuple[float, float, float]]] = {}
        #: robots whose agent came back (after a reboot, say), until a scan match places them
        #: again in their map: their scans since
        self.returning: dict[str, int] = {}
        #: a mission on a known map (``server.knownmap``): robots placed in it, kept there
        self.known = None if known is None else KnownMapDesk(cfg, self.fleet, self.merger,
                                                              self.events, known)
        if self.known is not None:   # its map is there to see (and plan on) from the start
            self.progress.hold = self.known.on_pass
            self.progress.update(0, MAP_TEAM)

    def use_pools(self, planner: Callable[[], Executor | None],
                  matcher: Callable[[int], Executor | None]) -> None:
        """Where slow work runs: ``planner()`` for replanning and lone robots' decisions,
        ``matcher(teams)`` for map matching between teams (None: here, in line). Given once,
        by the node, and after a snapshot is loaded (processes are not state)."""
        self.steering.planner = planner
        self.matcher.matcher = matcher

    # -- the loop --------------------------------------------------------------------------
    def on_scan(self, scan: Scan, now_ns: int | None = None) -> VelocityCommand:
        r = self.fleet.robots.get(scan.robot_id) or self.fleet.add_robot(scan.robot_id)
        if r.ghost:      # a robot named as the known map's parts: not one the server serves
            return VelocityCommand(robot_id=scan.robot_id, seq=0, stamp_ns=scan.stamp_ns,
                                   v_mps=0.0, omega_rps=0.0)
        ranges, angles = scan.ranges_m(), scan.angles_rad()
        # 1. SLAM on the scan without teammates' bodies; a new keyframe is matched against
        #    the teammates' maps
        self._localise(r, scan, ranges, angles)
        # 2. a robot placed at a known pose joins the robots placed so
        if not r.start_checked and r.robot_id in self.cfg.teams.start_poses:
            self.merger.join_known_start(r, scan.stamp_ns)
        r.last_stamp_ns = scan.stamp_ns
        r.view = LiveView(scan.stamp_ns, r.team_id, r.pose.copy(), ranges, angles,
                          scan.range_max_mm / 1000.0)
        self._record_online_pose(r, scan.stamp_ns)
        # 2b. on a known map: a robot not yet in it is matched against it, a robot in it is
        #     watched for being lost (and, extending the map, keeps the map up to date)
        if self.known is not None:
            self.known.on_scan(r, scan, ranges, angles,
                               scan.stamp_ns if now_ns is None else now_ns)
        # 3. sightings waiting for this scan: placed, and perhaps merged
        if self.desk.pending:
            self.desk.process(scan.stamp_ns)
        # 3b. one pair of teams' maps matched, every period: merges, planned meetings
        self.matcher.tick(scan.stamp_ns if now_ns is None else now_ns)
        # 4. coverage, termination and λ, every map period
        team = self.fleet.team_of(r)
        self.progress.tick(scan.stamp_ns if now_ns is None else now_ns, team.team_id)
        if team.finished:
            r.nav.finish("team coverage reached")
        # 4b. extending a known map: a placed robot with no errand passes over the map first
        if self.known is not None:
            self._inspect(r, scan.stamp_ns)
        # explored: where the robot passes again it re-uses keyframes rather than adds them
        r.slam.reusing = team.finished and r.slam.cfg.keyframes.reuse
        # 5. the command: the lookout's, or the navigator's — or a stop, for a scan the
        #    server got to too late to steer by
        cmd = self.steering.command(r, scan.stamp_ns, ranges, angles, self.navigate)
        if now_ns is not None and now_ns - scan.stamp_ns > self.cfg.control.max_scan_age_s * 1e9:
            r.late_scans += 1
            cmd = msgspec.structs.replace(cmd, v_mps=0.0, omega_rps=0.0)
        return cmd

    def _localise(self, r: RobotContext, scan: Scan, ranges: F64, angles: F64) -> None:
        prev = r.pose.copy()
        keyframes = len(r.slam.keyframes)
        unmatched = r.slam.stats.matches["odometry"]
        r.sensor_range_m = scan.range_max_mm / 1000.0
        team = self.fleet.team_of(r)
        r.slam.guides = [self.fleet.robots[m].slam for m in team.robot_ids
                         if m != r.robot_id] if len(team.robot_ids) > 1 else []
        r.pose = r.slam.add_scan(scan.stamp_ns, scan.odom_pose,
                                 self.fleet.without_teammates(r, ranges, angles), angles,
                                 scan.range_max_mm / 1000.0)
        if r.scans:
            r.distance_m += float(math.hypot(*(r.pose[:2] - prev[:2])))
        else:
            r.start_pose = r.pose.copy()
        if keyframes and len(r.slam.keyframes) > keyframes:
            self.surgery.match_teammates(r)
        r.scans += 1
        if r.robot_id in self.returning:
            self._placed_again(r, scan.stamp_ns, r.slam.stats.matches["odometry"] == unmatched)

    def _placed_again(self, r: RobotContext, stamp_ns: int, matched: bool) -> None:
        """A robot back after its agent was away: its first scan matched to its map places
        it again (an event); until then its scans are counted."""
        n = self.returning[r.robot_id] = self.returning[r.robot_id] + 1
        if not matched:
            return
        del self.returning[r.robot_id]
        x, y, th = (float(v) for v in r.pose)
        self.events.emit("robot_joined", [r.robot_id], r.team_id,
                         f"robot {r.robot_id} placed again in its map by scan {n} since it "
                         f"came back", stamp_ns, transform=(x, y, th))

    def _record_online_pose(self, r: RobotContext, stamp_ns: int) -> None:
        """The pose the server believes now, in the robot's own map frame, and in a team also
        where the team's map puts it (in its first robot's own frame)."""
        own = r.pose
        team = self.fleet.team_of(r)
        if len(team.robot_ids) > 1:
            own = compose(inverse(r.own_frame_in_team()), r.pose)
            first = self.fleet.robots.get(team.robot_ids[0])
            if first is not None and first is not r and len(first.online):
                rows = r.online_in.setdefault(first.robot_id, StampedRows(3))
                rows.append(stamp_ns, compose(inverse(first.own_frame_in_team()), r.pose)[:3])
        r.online.append(stamp_ns, own[:3])

    def on_tags(self, msg: TagDetections) -> None:
        """A robot's tag sightings (see ``server.rendezvous.desk``)."""
        self.desk.receive(msg)

    def _inspect(self, r: RobotContext, stamp_ns: int) -> None:
        """Its next place on the pass over the known map (``KnownMapDesk.inspect_goal``); a
        place not reached within ``INSPECT_GIVE_UP_S``, or come no nearer to for
        ``INSPECT_STALL_S`` (a door now closed), or left with little to see again
        (``KnownMapDesk.inspect_stale``), is given up."""
        assert self.known is not None
        e = self.orders.errands.get(r.robot_id)
        if e is not None and e.kind == "inspect":
            d = _left_m(e.path_xy, r.pose)
            if d < e.nearest_m - INSPECT_STALL_M:
                e.nearest_m, e.nearest_ns = d, stamp_ns
        if e is not None and e.kind == "inspect" and (
                stamp_ns - e.since_ns > INSPECT_GIVE_UP_S * 1e9 or
                stamp_ns - max(e.nearest_ns, e.since_ns) > INSPECT_STALL_S * 1e9 or
                self.known.inspect_stale(r)):
            del self.orders.errands[r.robot_id]
            e = None
        if e is None and (goal := self.known.inspect_goal(r)) is not None:
            try:
                self.orders.send(r, self.fleet, "inspect", goal, stamp_ns)
            except OperatorError as err:
                self.known.unreachable(goal, str(err))

    def operate(self, cmd: OperatorCommand, stamp_ns: int) -> tuple[int, str]:
        """Carry out an operator's order (``server.command.operator``); an event says what was done
        or why not. Returns (200, that line), or the refusal's status (``OperatorError``)
        and its line."""
        try:
            place = None if self.known is None else partial(place_by_hand, self.known,
                                                            now_ns=stamp_ns)
            status, line = 200, self.orders.apply(cmd, self.fleet, place)
        except OperatorError as e:
            status, line = e.status, f"{cmd.describe()} refused: {e}"
        self.events.emit("operator", [cmd.robot_id] if cmd.robot_id else [],
                         None, line, stamp_ns)
        return status, line

    def set_alive(self, robot_id: str, alive: bool) -> None:
        r = self.fleet.robots.get(robot_id)
        if alive and r is not None and not r.alive and r.scans:
            self.returning[robot_id] = 0
        self.fleet.set_alive(robot_id, alive)

    # -- state -----------------------------------------------------------------------------
    @property
    def robots(self) -> dict[str, RobotContext]:
        return self.fleet.robots

    @property
    def teams(self) -> dict[str, Team]:
        return self.fleet.teams

    @property
    def retired_teams(self) -> dict[str, Team]:
        return self.fleet.retired_teams

    @property
    def merges(self) -> list[MergeRecord]:
        return self.fleet.merges

    @property
    def tag_counters(self) -> dict[str, int]:
        """What became of the tag sightings and merge proposals, by name."""
        return self.counters.as_dict()

    @property
    def event_log(self) -> list[Event]:
        return self.events.all

    @property
    def map_stamp_ns(self) -> int:
        return self.progress.map_stamp_ns

    @property
    def finished(self) -> bool:
        """Every team with a live robot has finished (see ``Fleet.finished``)."""
        return self.fleet.finished

    def planning_grid(self, team_id: str) -> PlanningGrid:
        return self.fleet.planning_grid(team_id)

    # -- outputs ---------------------------------------------------------------------------
    def pop_events(self) -> list[Event]:
        return self.events.pop()

    def map_updates(self, teams: set[str] | None = None) -> list[MapUpdate]:
        """The latest grid of every team (or of ``teams``) as messages."""
        out = []
        for team in self.fleet.teams.values():
            if teams is not None and team.team_id not in teams:
                continue
            g = self.fleet.latest_grids.get(team.team_id)
            if g is None:
                continue
            out.append(MapUpdate.from_grid(g.data, team_id=team.team_id,
                                           seq=self.events.next_seq(),
                                           stamp_ns=self.map_stamp_ns,
                                           robot_ids=self._robots_of(team),
                                           resolution_m=g.resolution_m,
                                           origin=(g.origin_xy[0], g.origin_xy[1], 0.0)))
        return out

    def robot_states(self, stamp_ns: int) -> RobotStates:
        robots = []
        where = {} if self.known is None else localisation(self.known)
        for r in self.fleet.robots.values():
            if r.ghost:
                continue
            t = r.nav.target_xy
            mode: str = r.nav.mode.value
            errand = self.orders.errands.get(r.robot_id)
            if errand is not None:
                t, mode = errand.goal_xy, "returning"
            if self.orders.holds(r.robot_id):
                mode = "idle"
            robots.append(RobotEstimate(
                robot_id=r.robot_id, team_id=r.team_id,
                pose=(float(r.pose[0]), float(r.pose[1]), float(r.pose[2])),
                pose_sigma=self._pose_sigma(r),
                mode=mode if r.alive else "lost",  # type: ignore[arg-type]
                target=(float(t[0]), float(t[1])) if t is not None else None,
                distance_m=r.distance_m, keyframes=len(r.slam.keyframes),
                last_scan_stamp_ns=r.last_stamp_ns, **where.get(r.robot_id, {})))
        teams = [TeamCoverage(team_id=t.team_id, robot_ids=self._robots_of(t),
                              coverage=float(min(t.coverage, 1.0)), explored_m2=t.explored_m2)
                 for t in self.fleet.teams.values()]
        return RobotStates(seq=self.events.next_seq(), stamp_ns=stamp_ns, robots=robots,
                           teams=teams)

    def _robots_of(self, team: Team) -> list[str]:
        """A team's robots, without the ghosts that hold a known map's keyframes."""
        return [rid for rid in team.robot_ids if not self.fleet.robots[rid].ghost]

    def _pose_sigma(self, r: RobotContext) -> tuple[float, float, float]:
        """σ of the robot's newest keyframe pose from its graph's marginals (x, y [m], θ
        [rad]); worked out again only when the robot has a new keyframe."""
        n = len(r.slam.keyframes)
        cached = self._sigmas.get(r.robot_id)
        if cached is not None and cached[0] == n:
            return cached[1]
        sigma = (0.0, 0.0, 0.0)
        if n:
            try:
                sigma = r.slam.pose_sigma()
            except Exception:   # GTSAM may refuse an indeterminate system: no figure then
                sigma = (0.0, 0.0, 0.0)
        self._sigmas[r.robot_id] = (n, sigma)
        return sigma


def _left_m(path_xy: F64, pose: F64) -> float:
    """How far ``pose`` is from a path's end along it: to its nearest point, then on."""
    if not len(path_xy):
        return 0.0
    d = np.hypot(path_xy[:, 0] - pose[0], path_xy[:, 1] - pose[1])
    k = int(np.argmin(d))
    return float(d[k] + np.hypot(*np.diff(path_xy[k:], axis=0).T).sum())
