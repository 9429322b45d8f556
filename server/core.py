"""The server's orchestrator, free of I/O: scans in, velocity commands and map/state out.

One call per scan does the robot's whole loop:

    pose  = slam.add_scan(...)            # predict → match → keyframe → optimise → loop closure
    twist = navigator.step(...)           # explore (decide target, plan) → pursue → avoid
    cmd   = VelocityCommand(twist)        # stamped with the scan's stamp, with a time-to-live

Stamps reach the core in the server's time (``server.node`` maps each robot's clock onto it).
Periodic work (coverage and termination, map and state messages) runs on the ``now_ns`` the
caller passes: the server's own clock (the simulator's in lockstep, so a lockstep simulation
gives the same run every time); offline callers pass none and it runs on the scans' stamps.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.noise import NoiseError, robust
from factors.rendezvous import Sighting, rendezvous_factor
from factors.scan_match import loop_closure_factor, pose2, whitened_chi2
from schemas import (
    Event,
    MapUpdate,
    RobotEstimate,
    RobotStates,
    Scan,
    TagDetection,
    TagDetections,
    TeamCoverage,
    VelocityCommand,
)
from server.config import ServerConfig
from server.control import PursuitParams, StuckDetector, Twist, VfhParams
from server.coordination import Member, TeamExplorer, drop_target, own_explorer
from server.exploration import ExplorerParams, VisitedTargets, make_explorer
from server.exploration.analysis import AnalysisParams
from server.lookout import Lookout, LookParams
from server.navigator import DONE, Navigator
from server.planning import CostParams
from server.planning import OccupancyGrid as PlanningGrid
from server.slam import RobotSlam
from server.slam.backend import FactorRecord, robot_key_space
from server.slam.geometry import compose, inverse, transform_points
from server.slam.grid import GridParams, OccupancyGrid
from server.slam.mapping import GridMapper
from server.teams import (
    CHI2_3DOF_99,
    MergeProposal,
    MergeVerifier,
    SightingRecord,
    VerifierParams,
    chi2_between,
    cross_matches,
    join_graph,
    make_record,
    map_agreement,
    team_initial_values,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class RobotContext:
    robot_id: str
    slam: RobotSlam
    nav: Navigator
    team_id: str
    start_pose: F64 = field(default_factory=lambda: np.zeros(3))
    pose: F64 = field(default_factory=lambda: np.zeros(3))
    distance_m: float = 0.0
    scans: int = 0
    last_stamp_ns: int = 0
    alive: bool = True
    look: Lookout = field(default_factory=Lookout)
    start_checked: bool = False   # a known start pose was used (or there was none to use)
    #: the pose the server believed at each scan (stamp_ns, x, y, θ), in the robot's own map
    #: frame (its first pose is the origin; a merge does not move it)
    online: list[tuple[int, float, float, float]] = field(default_factory=list)

    def own_frame_in_team(self) -> F64:
        """The robot's own map frame (its first pose) in its team's frame, exactly: the first
        keyframe's team pose against where the robot's prior put it."""
        sl = self.slam
        return compose(sl.keyframe_pose(0), inverse(sl.trajectory.prior_pose()))


@dataclass
class Link:
    """A rendezvous factor inside a team's graph."""

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
    kind: str = "tags"            # tags | start (known start poses) | marker (given by hand)


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


class ServerCore:
    """Per-robot SLAM and navigation, per-team coverage; one thread calls it."""

    def __init__(self, cfg: ServerConfig, navigate: bool = True) -> None:
        self.cfg = cfg
        #: False: scans only feed SLAM, rendezvous and coverage (offline merging); commands are 0
        self.navigate = navigate
        self.robots: dict[str, RobotContext] = {}
        self.teams: dict[str, Team] = {}
        self.events: list[Event] = []
        self.event_log: list[Event] = []
        self._seq = 0
        self._robots_added = 0   # robot numbers are never reused: each owns its graph keys
        self._next_cover_ns = 0
        #: each team's grid as of ``map_stamp_ns`` (refreshed every ``map_period_s`` of scan time)
        self.latest_grids: dict[str, PlanningGrid] = {}
        self.map_stamp_ns = 0
        self._explorer_params = self._explorer_params_from(cfg)
        t = cfg.teams
        self.verifier = MergeVerifier(VerifierParams(min_sightings=t.min_sightings,
                                                     window_s=t.window_s))
        self._pose_sigmas = (t.pose_sigma_m, t.pose_sigma_m, math.radians(t.pose_sigma_deg))
        self._pending: list[tuple[int, str, TagDetection]] = []
        self._contradictions: dict[tuple[str, str], list[SightingRecord]] = {}
        self.merges: list[MergeRecord] = []
        self.retired_teams: dict[str, Team] = {}
        self.tag_counters: dict[str, int] = dict.fromkeys((
            "sightings", "used", "unknown_robot", "self", "bad", "expired", "within_team",
            "refined", "contradicting", "merges", "merges_rejected", "merges_undone",
            "map_matches", "too_far", "contradictions_overruled", "merges_deferred",
            "misread", "sightings_retired"), 0)

    # -- the loop --------------------------------------------------------------------------
    def on_scan(self, scan: Scan, now_ns: int | None = None) -> VelocityCommand:
        r = self.robots.get(scan.robot_id) or self._add_robot(scan.robot_id)
        prev = r.pose.copy()
        ranges, angles = scan.ranges_m(), scan.angles_rad()
        keyframes = len(r.slam.keyframes)
        r.pose = r.slam.add_scan(scan.stamp_ns, scan.odom_pose,
                                 self._without_teammates(r, ranges, angles), angles,
                                 scan.range_max_mm / 1000.0)
        if r.scans:
            r.distance_m += float(math.hypot(*(r.pose[:2] - prev[:2])))
        else:
            r.start_pose = r.pose.copy()
        if keyframes and len(r.slam.keyframes) > keyframes:
            self._match_teammates(r)
        r.scans += 1
        if not r.start_checked and r.robot_id in self.cfg.teams.start_poses:
            self._join_known_start(r, scan.stamp_ns)
        r.last_stamp_ns = scan.stamp_ns
        own = r.pose
        if len(self.teams[r.team_id].robot_ids) > 1:
            own = compose(inverse(r.own_frame_in_team()), r.pose)
        r.online.append((scan.stamp_ns, float(own[0]), float(own[1]), float(own[2])))
        if self._pending:
            self._process_pending(scan.stamp_ns)
        team = self.teams[r.team_id]
        self._periodic(scan.stamp_ns if now_ns is None else now_ns)
        if team.finished:
            r.nav.finish("team coverage reached")
        if not self.navigate:
            return VelocityCommand(robot_id=r.robot_id, seq=r.scans, stamp_ns=scan.stamp_ns,
                                   v_mps=0.0, omega_rps=0.0, ttl_s=self.cfg.control.command_ttl_s)
        ok = np.isfinite(ranges)
        pts = np.stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])], 1)
        look = self._look(r, scan.stamp_ns * 1e-9, pts)
        if look is not None:
            return VelocityCommand(robot_id=r.robot_id, seq=r.scans, stamp_ns=scan.stamp_ns,
                                   v_mps=look.v_mps, omega_rps=look.omega_rps,
                                   ttl_s=self.cfg.control.command_ttl_s)
        twist = r.nav.step(scan.stamp_ns * 1e-9, r.pose, r.start_pose, pts,
                           lambda: self.planning_grid(team.team_id), team.visited,
                           self._others_in_robot_frame(r))
        return VelocityCommand(robot_id=r.robot_id, seq=r.scans, stamp_ns=scan.stamp_ns,
                               v_mps=float(np.clip(twist.v_mps, -5, 5)),
                               omega_rps=float(np.clip(twist.omega_rps, -20, 20)),
                               ttl_s=self.cfg.control.command_ttl_s)

    def _look(self, r: RobotContext, now_s: float, points_robot: F64) -> Twist | None:
        """Turn toward something that moves while robots outside the team remain. A robot
        whose team is done keeps doing so: a robot still alone must be able to join it."""
        t = self.cfg.teams
        if not (t.enabled and t.look_at_movers) or r.nav.mode == "stuck":
            r.look.reset()
            return None
        if len(self.teams) < 2 and not r.look.active:
            return None
        team = self.teams[r.team_id]
        mates = np.array([self.robots[o].pose[:2] for o in team.robot_ids if o != r.robot_id],
                         dtype=np.float64).reshape(-1, 2)
        twist = r.look.step(now_s, r.pose, points_robot, self.latest_grids.get(r.team_id),
                            mates)
        if twist is None:
            if r.look.moved:  # the approach took the robot off its path: decide afresh
                r.look.moved = False
                drop_target(r.nav)
            return None
        if twist.v_mps > 0 and r.nav.vfh is not None:
            twist = r.nav.vfh.adjust(twist, r.look.heading_error, points_robot,
                                     self._others_in_robot_frame(r))
        return twist

    def _periodic(self, stamp_ns: int) -> None:
        if stamp_ns < self._next_cover_ns:
            return
        self._next_cover_ns = stamp_ns + int(self.cfg.map_period_s * 1e9)
        self.map_stamp_ns = stamp_ns
        total = self.cfg.explore.total_area_m2
        for team in self.teams.values():
            grid = self.latest_grids[team.team_id] = self.planning_grid(team.team_id)
            known = int(((grid.data >= 0) & ((grid.data < 40) | (grid.data > 70))).sum())
            team.explored_m2 = known * grid.resolution_m ** 2
            team.coverage = team.explored_m2 / total if total else 0.0
            team.history.append((stamp_ns, team.coverage))
            if total and not team.finished and team.coverage >= self.cfg.explore.coverage_threshold:
                self._finish_team(team, stamp_ns, f"coverage {team.coverage:.3f} reached")
            elif not team.finished and (alive := [
                    rid for rid in team.robot_ids if self.robots[rid].alive]) and all(
                    self.robots[rid].nav.mode == DONE for rid in alive):
                # (a robot that vanished does not hold its team back; one that comes back to
                # a finished team stops too)
                self._finish_team(team, stamp_ns, "no reachable frontier left")
        self._set_lambda()

    def _set_lambda(self) -> None:
        """λ of every robot's explorer: ``seek_lam`` while a robot that is alive is outside its
        team (the others are somewhere away from this robot's start; ranging out meets them
        sooner), ``lam`` once the team holds every robot."""
        e = self.cfg.explore
        alive_teams = {r.team_id for r in self.robots.values() if r.alive}
        for r in self.robots.values():
            lam = (e.seek_lam if e.seek_lam is not None and alive_teams - {r.team_id}
                   else e.lam)
            base = own_explorer(r.nav)
            if base.params.lam != lam:
                base.params = dataclasses.replace(base.params, lam=lam)

    def _finish_team(self, team: Team, stamp_ns: int, why: str) -> None:
        team.finished, team.finished_stamp_ns = True, stamp_ns
        for rid in team.robot_ids:
            self.robots[rid].nav.finish(why)
        self.emit("terminated", team.robot_ids, team.team_id, f"{team.team_id}: {why}",
                  stamp_ns)

    # -- robots and teams ------------------------------------------------------------------
    def _add_robot(self, robot_id: str) -> RobotContext:
        char, block = robot_key_space(self._robots_added)
        self._robots_added += 1
        c = self.cfg.control
        nav = Navigator(
            make_explorer(self.cfg.explore.explorer, self._explorer_params),
            PursuitParams(lookahead_m=c.lookahead_m, v_mps=c.v_mps, omega_max_rps=c.omega_max_rps,
                          goal_tolerance_m=c.goal_tolerance_m),
            VfhParams(robot_radius_m=c.robot_radius_m, v_mps=c.v_mps,
                      omega_max_rps=c.omega_max_rps) if c.vfh else None,
            StuckDetector(c.stuck_window_s, c.stuck_min_progress_m),
            self.cfg.explore.replan_period_s)
        team_id = f"team-{robot_id}"
        r = RobotContext(robot_id, RobotSlam(char, self.cfg.slam, key_block=block), nav,
                         team_id)
        t = self.cfg.teams
        r.look = Lookout(LookParams(max_range_m=t.max_sighting_range_m,
                                    omega_rps=min(1.0, c.omega_max_rps),
                                    approach_range_m=t.approach_range_m, approach_v_mps=c.v_mps,
                                    approach_stop_m=min(1.2, 0.7 * t.max_sighting_range_m)),
                         robot_id)
        self.robots[robot_id] = r
        self.teams[team_id] = Team(team_id, [robot_id],
                                   VisitedTargets(self.cfg.explore.visited_radius_m),
                                   anchor=robot_id, mapper=self._new_mapper())
        self.emit("robot_joined", [robot_id], team_id, f"robot {robot_id} joined", 0)
        log.debug("robot %s tracked as graph symbol %r (block %d) in %s", robot_id, char,
                  block, team_id)
        return r

    def set_alive(self, robot_id: str, alive: bool) -> None:
        r = self.robots.get(robot_id)
        if r is not None and r.alive != alive:
            r.alive = alive
            self.emit("robot_joined" if alive else "robot_lost", [robot_id], r.team_id,
                      f"robot {robot_id} {'is back' if alive else 'vanished'}", r.last_stamp_ns)

    def _without_teammates(self, r: RobotContext, ranges: F64, angles: F64) -> F64:
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

    def _others_in_robot_frame(self, r: RobotContext) -> F64:
        """Team mates' positions in ``r``'s body frame (for collision avoidance)."""
        team = self.teams[r.team_id]
        xy = [self.robots[o].pose[:2] for o in team.robot_ids
              if o != r.robot_id and self.robots[o].alive]
        if not xy:
            return np.zeros((0, 2))
        from server.slam.geometry import inverse

        return transform_points(inverse(r.pose), np.array(xy))

    def _new_mapper(self) -> GridMapper:
        return GridMapper(GridParams(**self.cfg.slam.grid.model_dump()))

    def team_grid(self, team_id: str) -> OccupancyGrid:
        """The team's log-odds grid from all its robots' keyframes, in the team frame."""
        team = self.teams[team_id]
        assert team.mapper is not None
        return team.mapper.update_many({
            rid: (self.robots[rid].slam.keyframes, self.robots[rid].slam.keyframe_poses())
            for rid in team.robot_ids})

    def planning_grid(self, team_id: str) -> PlanningGrid:
        """The team's occupancy grid in the nav2 convention (robots of one team share it)."""
        grid = self.team_grid(team_id)
        return PlanningGrid(grid.to_nav2(), grid.resolution_m,
                            (float(grid.origin[0]), float(grid.origin[1])))

    # -- rendezvous ------------------------------------------------------------------------
    def on_tags(self, msg: TagDetections) -> None:
        """Queue a robot's tag sightings until the scans around their time are in."""
        if not self.cfg.teams.enabled:
            return
        for det in msg.detections:
            self.tag_counters["sightings"] += 1
            if det.observed_robot_id == msg.robot_id:
                self.tag_counters["self"] += 1
                continue
            self._call(msg.robot_id, det)
            if det.range_m > self._usable_range_m(det):
                self.tag_counters["too_far"] += 1
                continue
            self._pending.append((msg.stamp_ns, msg.robot_id, det))
        latest = max((r.last_stamp_ns for r in self.robots.values()), default=0)
        self._process_pending(max(latest, msg.stamp_ns))

    def _usable_range_m(self, det: TagDetection) -> float:
        """How far a sighting may be to count: a tag's own range and centre are good only
        close up, the LIDAR's off the robot's body much farther."""
        t = self.cfg.teams
        if det.located_by == "lidar":
            return max(t.max_sighting_range_m, t.max_lidar_sighting_range_m)
        return t.max_sighting_range_m

    def _call(self, observer: str, det: TagDetection) -> None:
        """A robot of another team was seen: tell both robots where the other one is, so they
        close in until the tags can be read well (see server.lookout)."""
        t = self.cfg.teams
        a, b = self.robots.get(observer), self.robots.get(det.observed_robot_id)
        if a is None or b is None or a.team_id == b.team_id or not t.look_at_movers or \
                t.approach_range_m <= 0 or not a.scans or not b.scans:
            return
        if not all(math.isfinite(v) for v in (det.range_m, det.bearing_rad, det.yaw_rad)):
            return   # counted as bad where the sighting itself is refused
        rel = np.array([det.range_m * math.cos(det.bearing_rad),
                        det.range_m * math.sin(det.bearing_rad), det.yaw_rad])
        now_a, now_b = a.last_stamp_ns * 1e-9, b.last_stamp_ns * 1e-9
        a.look.hear(now_a, transform_points(a.pose, rel[None, :2])[0],
                    max(0.5, 0.1 * det.range_m), sure=True)
        # the reader as the seen robot would place it: through the tag's heading, which is
        # poor at range, hence the wide tolerance
        back = inverse(rel)
        b.look.hear(now_b, transform_points(b.pose, back[None, :2])[0],
                    max(1.0, 0.35 * det.range_m), sure=False, range_m=det.range_m,
                    range_tolerance_m=3.0 * det.sigma_range_m + 0.2)

    def _process_pending(self, now_ns: int) -> None:
        t = self.cfg.teams
        keep = []
        for stamp, observer, det in self._pending:
            a, b = self.robots.get(observer), self.robots.get(det.observed_robot_id)
            if a is None or b is None:
                if now_ns - stamp > t.max_pending_s * 1e9:
                    self.tag_counters["unknown_robot"] += 1
                    log.info("sighting of unknown robot %s by %s dropped",
                             det.observed_robot_id, observer)
                else:
                    keep.append((stamp, observer, det))
                continue
            tol = int(t.sighting_tolerance_s * 1e9)
            at_a, at_b = a.slam.pose_at(stamp, tol), b.slam.pose_at(stamp, tol)
            if at_a is None or at_b is None:
                if min(a.last_stamp_ns, b.last_stamp_ns) > stamp + tol or \
                        now_ns - stamp > t.max_pending_s * 1e9:
                    self.tag_counters["expired"] += 1
                else:
                    keep.append((stamp, observer, det))
                continue
            try:
                self._sighting(stamp, a, b, det, at_a, at_b)
            except NoiseError as e:
                self.tag_counters["bad"] += 1
                log.warning("sighting by %s refused: %s", observer, e)
        self._pending = keep

    def _sighting(self, stamp: int, a: RobotContext, b: RobotContext, det: TagDetection,
                  at_a: tuple[int, F64], at_b: tuple[int, F64]) -> None:
        s = Sighting(det.range_m, det.bearing_rad, det.yaw_rad, det.sigma_range_m,
                     det.sigma_bearing_rad, det.sigma_yaw_rad)
        P_a = compose(a.slam.keyframe_pose(at_a[0]), at_a[1])
        P_b = compose(b.slam.keyframe_pose(at_b[0]), at_b[1])
        rec = make_record(stamp, a.robot_id, b.robot_id, s, at_a, at_b, P_a, P_b,
                          self._pose_sigmas)
        self.tag_counters["used"] += 1
        same_team = a.team_id == b.team_id
        if not (same_team and self._agrees(rec)):
            mate = self._teammate_there(a, rec)
            if mate is not None:
                # two robots are never in one place: the tag is the teammate's, misread
                self.tag_counters["misread"] += 1
                log.info("sighting of %s by %s at %s's place: taken for a misread tag",
                         b.robot_id, a.robot_id, mate)
                return
        if same_team:
            if det.range_m > self.cfg.teams.max_sighting_range_m:
                # from afar (located by the LIDAR) a sighting helps find a team; within one,
                # the maps matched against each other say more
                self.tag_counters["within_team"] += 1
                return
            self._within_team(rec)
            return
        proposal = self.verifier.add(a.team_id, b.team_id, rec)
        if proposal is not None:
            self.try_merge(proposal, stamp)

    def _link(self, rec: SightingRecord) -> Link:
        a, b = self.robots[rec.observer], self.robots[rec.observed]
        f = rendezvous_factor(a.slam.trajectory.key(rec.kf_a), b.slam.trajectory.key(rec.kf_b),
                              rec.sighting, rec.T_kf_a, rec.T_kf_b, kernel="huber")
        return Link(rec.observer, rec.observed, rec.stamp_ns, FactorRecord(f, "rendezvous"))

    def own_frames_link(self, a: str, b: str, T_own: F64, sigmas: F64, kind: str,
                        stamp_ns: int) -> tuple[F64, Link]:
        """A robust between-factor of the robots' first keyframes saying that b's own map
        frame is ``T_own`` in a's own map frame (known start poses, a marker measured by
        hand), and what it makes of the team transform (b's team frame -> a's)."""
        ra, rb = self.robots[a], self.robots[b]
        T_team = compose(compose(ra.own_frame_in_team(), T_own),
                         inverse(rb.own_frame_in_team()))
        T_link = compose(inverse(ra.slam.keyframe_pose(0)),
                         compose(T_team, rb.slam.keyframe_pose(0)))
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))
        f = gtsam.BetweenFactorPose2(ra.slam.trajectory.key(0), rb.slam.trajectory.key(0),
                                     pose2(T_link), robust(noise, "huber"))
        return T_team, Link(a, b, stamp_ns, FactorRecord(f, kind))

    def _join_known_start(self, r: RobotContext, stamp_ns: int) -> None:
        """A robot placed at a known pose joins the team of the robots already placed so, as
        soon as it has a keyframe (the merge is still checked on the maps)."""
        t = self.cfg.teams
        starts = t.start_poses
        if not r.slam.keyframes:
            return  # its first scan was refused: try again with the next
        r.start_checked = True
        other = next((o for o in self.robots.values() if o is not r and o.robot_id in starts
                      and o.slam.keyframes and o.team_id != r.team_id), None)
        if other is None:
            return  # the first one placed: the others join it
        S_a = np.asarray(starts[other.robot_id], dtype=np.float64)
        S_b = np.asarray(starts[r.robot_id], dtype=np.float64)
        sig = np.array([t.start_pose_sigma_m, t.start_pose_sigma_m,
                        math.radians(t.start_pose_sigma_deg)])
        T_team, link = self.own_frames_link(other.robot_id, r.robot_id,
                                            compose(inverse(S_a), S_b), sig, "start", stamp_ns)
        self.try_merge(MergeProposal(other.team_id, r.team_id, (), T_team, np.diag(sig ** 2),
                                     T_team), stamp_ns, (link,), kind="start")

    def try_merge(self, p: MergeProposal, stamp: int, extra_links: tuple[Link, ...] = (),
                  kind: str = "tags") -> None:
        """Verify and commit a merge; ``extra_links`` join the graphs besides the proposal's
        sightings (a marker measured by hand between two recorded sessions)."""
        t = self.cfg.teams
        ta, tb = self.teams[p.team_a], self.teams[p.team_b]
        agree = map_agreement(self.team_grid(ta.team_id), self.team_grid(tb.team_id), p.T_ab)
        info = {"overlap_cells": agree.overlap_cells, "wall_cells": agree.occupied_checked,
                "conflicts": agree.conflicts, "conflict_ratio": round(agree.conflict_ratio, 4)}
        if agree.occupied_checked >= t.min_checked_cells and \
                agree.conflict_ratio > t.max_conflict_ratio:
            self._refuse(p, f"maps disagree ({agree.conflicts} of {agree.occupied_checked} "
                         "wall cells)", stamp)
            return
        tried = [0]
        matches = [m for ra in ta.robot_ids for rb in tb.robot_ids
                   for m in cross_matches(self.robots[ra].slam, self.robots[rb].slam,
                                          T_ab=p.T_ab, tried=tried)]
        found = len(matches)
        info["map_match_tries"], info["map_matches_before"] = tried[0], found
        if tried[0] >= t.min_map_match_tries and found == 0:
            self._refuse(p, f"no part of the maps matches within 0.5 m ({tried[0]} tried)",
                         stamp)
            return
        if matches:
            # where the maps do match, they say how the transform turns: far better than the
            # sightings (a small error across the line of sight turns it by degrees)
            turn = float(np.median([m.turn_rad for m in matches]))
            info["map_turn_deg"] = round(math.degrees(turn), 3)
            bound = t.max_map_turn_sigmas * math.sqrt(p.cov_ab[2, 2]) + math.radians(1.0)
            if abs(turn) > bound:
                self._refuse(p, f"the maps turn the transform by {math.degrees(turn):.2f}° "
                             f"({found} matches), beyond its uncertainty "
                             f"({math.degrees(bound):.2f}°)", stamp)
                return
        far = max((r.sighting.range_m for r in p.records), default=0.0)
        if far > t.max_sighting_range_m and found == 0 and kind == "tags":
            # sightings from afar (located by the LIDAR): a small error across the line of
            # sight turns the maps by a degree; wait until a map match confirms them
            self.tag_counters["merges_deferred"] += 1
            return
        b_anchor = self.robots[tb.anchor]
        b_origin_before = b_anchor.slam.keyframe_pose(0)
        links = [self._link(r) for r in p.records] + list(extra_links)
        self._rebuild(ta, [(rid, np.zeros(3)) for rid in ta.robot_ids]
                      + [(rid, p.T_ab) for rid in tb.robot_ids],
                      ta.links + tb.links + links)
        info["map_matches"] = self._refine_on_maps(ta.robot_ids, tb.robot_ids, links)
        info["sightings_retired"] = self._retire_sightings(ta.links + tb.links + links)
        T_joint = compose(b_anchor.slam.keyframe_pose(0), inverse(b_origin_before))
        for rid in tb.robot_ids:
            r = self.robots[rid]
            r.team_id = ta.team_id
            r.start_pose = compose(p.T_ab, r.start_pose)
            r.pose = r.slam.pose
        for xy in tb.visited.points_xy:
            ta.visited.add(transform_points(p.T_ab, np.asarray(xy).reshape(1, 2))[0])
        merged_ids = list(tb.robot_ids)
        ta.robot_ids = ta.robot_ids + merged_ids
        ta.links = [ln for ln in ta.links + tb.links + links if not ln.retired]
        tb.merged_into = ta.team_id
        self.retired_teams[tb.team_id] = self.teams.pop(tb.team_id)
        self.latest_grids.pop(tb.team_id, None)
        self.verifier.forget(tb.team_id)
        self._coordinate(ta)
        rec = MergeRecord(stamp, ta.team_id, tb.team_id, [r for r in ta.robot_ids
                                                          if r not in merged_ids], merged_ids,
                          [(r.observer, r.observed, r.stamp_ns) for r in p.records],
                          p.T_ab, p.cov_ab, p.direct_first, T_joint, info, kind=kind)
        self.merges.append(rec)
        self.tag_counters["merges"] += 1
        how = f"{len(p.records)} sightings" if kind == "tags" else f"a {kind} link"
        log.info("merged %s into %s from %s: T %s (before %s)", tb.team_id, ta.team_id, how,
                 T_joint.round(3), p.T_ab.round(3))
        self._seq += 1
        ev = Event(kind="merge", robot_ids=ta.robot_ids, team_id=ta.team_id,
                   message=f"{tb.team_id} merged into {ta.team_id} from {how}",
                   transform=(float(T_joint[0]), float(T_joint[1]), float(T_joint[2])),
                   covariance=[float(v) for v in p.cov_ab.reshape(-1)], seq=self._seq,
                   stamp_ns=stamp)
        self.events.append(ev)
        self.event_log.append(ev)

    def _refuse(self, p: MergeProposal, why: str, stamp: int) -> None:
        ta, tb = self.teams[p.team_a], self.teams[p.team_b]
        self.verifier.reject(p)
        self.tag_counters["merges_rejected"] += 1
        log.info("%s not merged into %s: %s (T %s from %d sightings)", tb.team_id, ta.team_id,
                 why, np.asarray(p.T_ab).round(3), len(p.records))
        self.emit("merge_rejected", ta.robot_ids + tb.robot_ids, ta.team_id,
                  f"{tb.team_id} not merged into {ta.team_id}: {why}", stamp)

    def _match_teammates(self, r: RobotContext) -> None:
        """Every ``team_match_every`` new keyframes of a robot in a team of several: match the
        newest against its teammates' maps where they overlap. Without this, each robot's map
        would drift on its own after the merge, and the joint map would come apart where two
        robots went past the same walls at different times."""
        every = self.cfg.teams.team_match_every
        team = self.teams[r.team_id]
        k = len(r.slam.keyframes) - 1
        if every <= 0 or len(team.robot_ids) < 2 or k % every:
            return
        mates = [o for o in team.robot_ids if o != r.robot_id]
        if self._refine_on_maps(mates, [r.robot_id], team.links, only=[k]) and \
                self._retire_sightings(team.links):
            team.links = [ln for ln in team.links if not ln.retired]

    def _tied_by_maps(self, links: list[Link], a: str, b: str) -> bool:
        """Whether map matches join robots a and b's graphs often enough that the tag
        sightings between them no longer count (``teams.retire_sightings_after``)."""
        need = self.cfg.teams.retire_sightings_after
        return need > 0 and sum(ln.record.kind == "cross" and {ln.a, ln.b} == {a, b}
                                for ln in links) >= need

    def _retire_sightings(self, links: list[Link]) -> int:
        """Take the tag sightings out of the graph for every robot pair the maps now tie
        (``_tied_by_maps``); they are marked ``retired`` (the caller drops them from the
        team's links). A meeting's sightings share their error (one geometry, seen from one
        place): kept beside map matches, they hold the two maps a fraction of a degree off
        where the robots met while the matches elsewhere pull them right, and both maps bend.
        Returns how many were taken out."""
        out = [ln for ln in links if ln.record.kind == "rendezvous" and not ln.retired
               and self._tied_by_maps(links, ln.a, ln.b)]
        if not out:
            return 0
        graph = self.robots[out[0].a].slam.graph
        graph.remove([ln.record.index for ln in out if ln.record.index is not None])
        for ln in out:
            ln.retired, ln.record.index = True, None
        graph.iterate(self.cfg.slam.graph.extra_iterations_after_loop)
        for rc in self.robots.values():
            if rc.slam.graph is graph:
                rc.slam.rebind(graph)
                rc.pose = rc.slam.pose
        self.tag_counters["sightings_retired"] += len(out)
        log.info("%d tag sightings left the graph: the maps tie %s", len(out),
                 ", ".join(sorted({"+".join(sorted((ln.a, ln.b))) for ln in out})))
        return len(out)

    def _refine_on_maps(self, side_a: list[str], side_b: list[str], links: list[Link],
                        only: list[int] | None = None) -> int:
        """Match each joining robot's keyframes (or the ones in ``only``) against the other
        side's map where they overlap, and add the matches as robust between-factors (``links``
        gets them); those still inconsistent after optimisation are taken out. Returns how
        many were kept."""
        if not self.cfg.teams.refine_on_maps:
            return 0
        g = self.cfg.slam.graph
        loop = self.cfg.slam.loop
        floor = np.array([g.match_sigma_floor_m, g.match_sigma_floor_m,
                          math.radians(g.match_sigma_floor_deg)])
        added: list[Link] = []
        graph = None
        for ra in side_a:
            for rb in side_b:
                a, b = self.robots[ra].slam, self.robots[rb].slam
                graph = a.graph
                for m in cross_matches(a, b, only=only):
                    f = loop_closure_factor(a.trajectory.key(m.ka), b.trajectory.key(m.kb),
                                            m.T_ka_kb, m.information, loop.sigma_scale ** 2,
                                            floor, "huber", loop.huber_k)
                    rec = FactorRecord(f, "cross")
                    (rec.index,) = graph.add([f], {})
                    added.append(Link(ra, rb, 0, rec))
        if graph is None or not added:
            return 0
        graph.iterate(g.extra_iterations_after_loop)
        est = graph.estimate()
        bad = [ln for ln in added if whitened_chi2(ln.record.factor, est) > loop.max_chi2]
        if bad:
            graph.remove([ln.record.index for ln in bad if ln.record.index is not None])
            graph.iterate(g.extra_iterations_after_loop)
        kept = [ln for ln in added if ln not in bad]
        links.extend(kept)
        for rid in side_a + side_b:
            r = self.robots[rid]
            r.slam.rebind(graph)
            r.pose = r.slam.pose
        self.tag_counters["map_matches"] += len(kept)
        return len(kept)

    def _rebuild(self, team: Team, frames: list[tuple[str, F64]], links: list[Link]) -> None:
        """One joint graph for ``frames`` (robot, transform of its current frame into the
        team's), anchored on ``team.anchor``, with ``links``; every robot continues in it."""
        slams = [(self.robots[rid].slam, T) for rid, T in frames]
        graph = join_graph([sl for sl, _ in slams], self.robots[team.anchor].slam,
                           [ln.record for ln in links], team_initial_values(slams),
                           self.cfg.slam.graph.relinearize_threshold)
        for rid, _ in frames:
            r = self.robots[rid]
            r.slam.rebind(graph)
            r.pose = r.slam.pose
            drop_target(r.nav)
            r.look.forget()

    def _coordinate(self, team: Team) -> None:
        """Robots of a team of several decide together (see ``server.coordination``)."""
        for rid in team.robot_ids:
            nav = self.robots[rid].nav
            base = own_explorer(nav)
            if len(team.robot_ids) > 1:
                nav.explorer = TeamExplorer(  # type: ignore[assignment]
                    base, rid, functools.partial(self._members, team.team_id),
                    self.cfg.teams.coordination)
            else:
                nav.explorer = base

    def _members(self, team_id: str) -> list[Member]:
        team = self.teams.get(team_id)
        if team is None:
            return []
        return [Member(rid, self.robots[rid].pose, self.robots[rid].start_pose,
                       self.robots[rid].nav)
                for rid in team.robot_ids if self.robots[rid].alive]

    def _within_team(self, rec: SightingRecord) -> None:
        """A sighting between teammates: another factor if it agrees with the team's graph;
        consistent disagreement undoes the merge that joined them."""
        t = self.cfg.teams
        self.tag_counters["within_team"] += 1
        team = self.teams[self.robots[rec.observer].team_id]
        pair = (min(rec.observer, rec.observed), max(rec.observer, rec.observed))
        if self._agrees(rec):
            self._contradictions.pop(pair, None)
            last = max((ln.stamp_ns for ln in team.links if {ln.a, ln.b} == set(pair)),
                       default=None)
            if self._tied_by_maps(team.links, *pair):
                return   # the maps say more about this pair than another sighting would
            if last is None or rec.stamp_ns - last >= t.refine_period_s * 1e9:
                ln = self._link(rec)
                a = self.robots[rec.observer]
                (idx,) = a.slam.graph.add([ln.record.factor], {})
                ln.record.index = idx
                team.links.append(ln)
                self.tag_counters["refined"] += 1
            return
        self.tag_counters["contradicting"] += 1
        bad = self._contradictions.setdefault(pair, [])
        bad.append(rec)
        bad[:] = [r for r in bad if r.stamp_ns >= rec.stamp_ns - t.window_s * 1e9]
        agreeing = [r for r in bad
                    if chi2_between(r.T_ab, r.cov_ab, rec.T_ab, rec.cov_ab) <= CHI2_3DOF_99]
        if len(agreeing) >= t.undo_after:
            self._undo(team, rec, pair)

    def _agrees(self, rec: SightingRecord) -> bool:
        """Whether a sighting between teammates agrees with where the team's graph has them."""
        vp = self.verifier.p
        miss = float(np.hypot(*(rec.p_seen_a - rec.p_own_b)))
        agrees = miss <= vp.gate_sigmas * rec.sigma_p_m + vp.gate_floor_m
        if agrees and rec.sighting.sigma_yaw_rad <= vp.informative_yaw_rad:
            agrees = abs(math.remainder(rec.T_ab[2], 2 * math.pi)) <= \
                vp.gate_sigmas * math.sqrt(rec.cov_ab[2, 2]) + math.radians(2)
        return agrees

    def _teammate_there(self, a: RobotContext, rec: SightingRecord) -> str | None:
        """A teammate of the observer (other than the robot named) that its team's graph puts
        where the sighting saw the tag, at the sighting's time: a misread tag id reads as a
        robot standing exactly where a teammate is."""
        vp = self.verifier.p
        gate = vp.gate_sigmas * rec.sigma_p_m + vp.gate_floor_m
        tol = int(self.cfg.teams.sighting_tolerance_s * 1e9)
        for cid in self.teams[a.team_id].robot_ids:
            if cid in (rec.observer, rec.observed):
                continue
            c = self.robots[cid]
            at = c.slam.pose_at(rec.stamp_ns, tol)
            if at is None:
                continue
            p = compose(c.slam.keyframe_pose(at[0]), at[1])[:2]
            if float(np.hypot(*(p - rec.p_seen_a))) <= gate:
                return cid
        return None

    def _maps_still_match(self, side_a: list[str], side_b: list[str]) -> bool:
        """Whether keyframes of one side still match the other side's map (within 0.5 m)
        where they overlap, in the joint estimate."""
        tried = [0]
        found = sum(len(cross_matches(self.robots[a].slam, self.robots[b].slam, tried=tried))
                    for a in side_a for b in side_b)
        return tried[0] >= self.cfg.teams.min_map_match_tries and \
            found >= max(1, tried[0] // 4)

    def _undo(self, team: Team, rec: SightingRecord, pair: tuple[str, str]) -> None:
        """Split ``team`` back along the latest merge that put ``pair`` together."""
        merge = next((m for m in reversed(self.merges) if m.team_id == team.team_id
                      and m.undone_stamp_ns is None
                      and (pair[0] in m.robots_b) != (pair[1] in m.robots_b)), None)
        self._contradictions.pop(pair, None)
        if merge is None or any(m.team_id == team.team_id and m.stamp_ns > merge.stamp_ns
                                and m.undone_stamp_ns is None for m in self.merges):
            log.warning("sightings contradict team %s but its latest merge does not separate "
                        "%s and %s: kept", team.team_id, *pair)
            return
        side_b = [r for r in team.robot_ids if r in merge.robots_b]
        side_a = [r for r in team.robot_ids if r not in merge.robots_b]
        if self.cfg.teams.refine_on_maps and self._maps_still_match(side_a, side_b):
            # the maps fit where they overlap: more likely a tag misread as a teammate's
            self.tag_counters["contradictions_overruled"] += 1
            log.warning("sightings contradict %s and %s in %s, but their maps still match: "
                        "merge kept", *pair, team.team_id)
            return
        old = self.retired_teams.pop(merge.joined_team_id)
        b_anchor = self.robots[old.anchor]
        T_team_b = compose(b_anchor.slam.keyframe_pose(0),
                           inverse(b_anchor.slam.trajectory.prior_pose()))
        inside_a = [ln for ln in team.links if ln.a in side_a and ln.b in side_a]
        inside_b = [ln for ln in team.links if ln.a in side_b and ln.b in side_b]
        for ln in team.links:
            if ln not in inside_a and ln not in inside_b:
                ln.record.index = None
        back = inverse(T_team_b)
        old.robot_ids, old.links, old.merged_into = side_b, inside_b, None
        old.mapper = self._new_mapper()
        team.robot_ids, team.links = side_a, inside_a
        for t_ in (team, old):  # each part judges its own coverage again
            t_.finished, t_.finished_stamp_ns = False, None
        for rid in side_a + side_b:
            self.robots[rid].nav.resume()
        team.mapper = self._new_mapper()
        self.teams[old.team_id] = old
        self._rebuild(team, [(rid, np.zeros(3)) for rid in side_a], inside_a)
        self._rebuild(old, [(rid, back) for rid in side_b], inside_b)
        for rid in side_b:
            r = self.robots[rid]
            r.team_id = old.team_id
            r.start_pose = compose(back, r.start_pose)
        self._coordinate(team)
        self._coordinate(old)
        merge.undone_stamp_ns = rec.stamp_ns
        self.tag_counters["merges_undone"] += 1
        log.warning("%s split from %s: sightings between %s and %s contradict the merge",
                    old.team_id, team.team_id, *pair)
        self.emit("merge_undone", side_a + side_b, team.team_id,
                  f"{old.team_id} split from {team.team_id}: sightings contradict the merge",
                  rec.stamp_ns)

    @staticmethod
    def _explorer_params_from(cfg: ServerConfig) -> ExplorerParams:
        e, c = cfg.explore, cfg.control
        analysis = AnalysisParams(cost=CostParams(robot_radius_m=c.robot_radius_m,
                                                  unknown_is_obstacle=e.unknown_as_obstacle))
        return ExplorerParams(analysis=analysis, lam=e.lam, total_area_m2=e.total_area_m2,
                              coverage_threshold=e.coverage_threshold,
                              frontier_view=e.frontier_view)

    # -- outputs ---------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        """Every team with a live robot has finished (and there is one). A team whose robots
        all vanished cannot go on, so it does not hold the others' end back."""
        live = [t for t in self.teams.values()
                if any(self.robots[rid].alive for rid in t.robot_ids)]
        return bool(live) and all(t.finished for t in live)

    def emit(self, kind: str, robot_ids: list[str], team_id: str | None, message: str,
             stamp_ns: int) -> None:
        self._seq += 1
        ev = Event(kind=kind, robot_ids=robot_ids, team_id=team_id, message=message,  # type: ignore[arg-type]
                   seq=self._seq, stamp_ns=max(stamp_ns, 0))
        self.events.append(ev)
        self.event_log.append(ev)

    def pop_events(self) -> list[Event]:
        out, self.events = self.events, []
        return out

    def map_updates(self) -> list[MapUpdate]:
        """The latest grid of every team as messages."""
        out = []
        for team in self.teams.values():
            g = self.latest_grids.get(team.team_id)
            if g is None:
                continue
            self._seq += 1
            out.append(MapUpdate.from_grid(g.data, team_id=team.team_id, seq=self._seq,
                                           stamp_ns=self.map_stamp_ns,
                                           robot_ids=team.robot_ids,
                                           resolution_m=g.resolution_m,
                                           origin=(g.origin_xy[0], g.origin_xy[1], 0.0)))
        return out

    def robot_states(self, stamp_ns: int) -> RobotStates:
        robots = []
        for r in self.robots.values():
            t = r.nav.target_xy
            mode = r.nav.mode if r.alive else "lost"
            robots.append(RobotEstimate(
                robot_id=r.robot_id, team_id=r.team_id,
                pose=(float(r.pose[0]), float(r.pose[1]), float(r.pose[2])),
                mode=mode,  # type: ignore[arg-type]
                target=(float(t[0]), float(t[1])) if t is not None else None,
                distance_m=r.distance_m, keyframes=len(r.slam.keyframes),
                last_scan_stamp_ns=r.last_stamp_ns))
        teams = [TeamCoverage(team_id=t.team_id, robot_ids=t.robot_ids,
                              coverage=float(min(t.coverage, 1.0)), explored_m2=t.explored_m2)
                 for t in self.teams.values()]
        self._seq += 1
        return RobotStates(seq=self._seq, stamp_ns=stamp_ns, robots=robots, teams=teams)
