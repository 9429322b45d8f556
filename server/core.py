"""The server's orchestrator, free of I/O: scans in, velocity commands and map/state out.

One call per scan does the robot's whole loop:

    pose  = slam.add_scan(...)            # predict → match → keyframe → optimise → loop closure
    twist = navigator.step(...)           # explore (decide target, plan) → pursue → avoid
    cmd   = VelocityCommand(twist)        # stamped with the scan's stamp, with a time-to-live

Periodic work (coverage and termination, map and state messages) is driven by the scans'
stamps, not the wall clock, so a lockstep simulation gives the same run every time.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas import (
    Event,
    MapUpdate,
    RobotEstimate,
    RobotStates,
    Scan,
    TeamCoverage,
    VelocityCommand,
)
from server.config import ServerConfig
from server.control import PursuitParams, StuckDetector, VfhParams
from server.exploration import ExplorerParams, VisitedTargets, make_explorer
from server.exploration.analysis import AnalysisParams
from server.navigator import DONE, Navigator
from server.planning import CostParams
from server.planning import OccupancyGrid as PlanningGrid
from server.slam import RobotSlam
from server.slam.geometry import transform_points

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
ROBOT_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"


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
    #: the pose the server believed at each scan (stamp_ns, x, y, θ), in the team frame
    online: list[tuple[int, float, float, float]] = field(default_factory=list)


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


class ServerCore:
    """Per-robot SLAM and navigation, per-team coverage; one thread calls it."""

    def __init__(self, cfg: ServerConfig) -> None:
        self.cfg = cfg
        self.robots: dict[str, RobotContext] = {}
        self.teams: dict[str, Team] = {}
        self.events: list[Event] = []
        self.event_log: list[Event] = []
        self._seq = 0
        self._next_cover_ns = 0
        #: each team's grid as of ``map_stamp_ns`` (refreshed every ``map_period_s`` of scan time)
        self.latest_grids: dict[str, PlanningGrid] = {}
        self.map_stamp_ns = 0
        self._explorer_params = self._explorer_params_from(cfg)

    # -- the loop --------------------------------------------------------------------------
    def on_scan(self, scan: Scan) -> VelocityCommand:
        r = self.robots.get(scan.robot_id) or self._add_robot(scan.robot_id)
        prev = r.pose.copy()
        ranges, angles = scan.ranges_m(), scan.angles_rad()
        r.pose = r.slam.add_scan(scan.stamp_ns, scan.odom_pose, ranges, angles,
                                 scan.range_max_mm / 1000.0)
        if r.scans:
            r.distance_m += float(math.hypot(*(r.pose[:2] - prev[:2])))
        else:
            r.start_pose = r.pose.copy()
        r.scans += 1
        r.last_stamp_ns = scan.stamp_ns
        r.online.append((scan.stamp_ns, float(r.pose[0]), float(r.pose[1]), float(r.pose[2])))
        team = self.teams[r.team_id]
        self._periodic(scan.stamp_ns)
        if team.finished:
            r.nav.finish("team coverage reached")
        ok = np.isfinite(ranges)
        pts = np.stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])], 1)
        twist = r.nav.step(scan.stamp_ns * 1e-9, r.pose, r.start_pose, pts,
                           lambda: self.planning_grid(team.team_id), team.visited,
                           self._others_in_robot_frame(r))
        return VelocityCommand(robot_id=r.robot_id, seq=r.scans, stamp_ns=scan.stamp_ns,
                               v_mps=float(np.clip(twist.v_mps, -5, 5)),
                               omega_rps=float(np.clip(twist.omega_rps, -20, 20)),
                               ttl_s=self.cfg.control.command_ttl_s)

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
            elif not team.finished and all(
                    self.robots[rid].nav.mode == DONE for rid in team.robot_ids):
                self._finish_team(team, stamp_ns, "no reachable frontier left")

    def _finish_team(self, team: Team, stamp_ns: int, why: str) -> None:
        team.finished, team.finished_stamp_ns = True, stamp_ns
        for rid in team.robot_ids:
            self.robots[rid].nav.finish(why)
        self.emit("terminated", team.robot_ids, team.team_id, f"{team.team_id}: {why}",
                  stamp_ns)

    # -- robots and teams ------------------------------------------------------------------
    def _add_robot(self, robot_id: str) -> RobotContext:
        if len(self.robots) >= len(ROBOT_CHARS):
            raise ValueError(f"cannot track more than {len(ROBOT_CHARS)} robots")
        char = ROBOT_CHARS[len(self.robots)]
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
        r = RobotContext(robot_id, RobotSlam(char, self.cfg.slam), nav, team_id)
        self.robots[robot_id] = r
        self.teams[team_id] = Team(team_id, [robot_id],
                                   VisitedTargets(self.cfg.explore.visited_radius_m))
        self.emit("robot_joined", [robot_id], team_id, f"robot {robot_id} joined", 0)
        log.info("robot %s tracked as graph symbol %r in %s", robot_id, char, team_id)
        return r

    def set_alive(self, robot_id: str, alive: bool) -> None:
        r = self.robots.get(robot_id)
        if r is not None and r.alive != alive:
            r.alive = alive
            self.emit("robot_joined" if alive else "robot_lost", [robot_id], r.team_id,
                      f"robot {robot_id} {'is back' if alive else 'vanished'}", r.last_stamp_ns)

    def _others_in_robot_frame(self, r: RobotContext) -> F64:
        """Team mates' positions in ``r``'s body frame (for collision avoidance)."""
        team = self.teams[r.team_id]
        xy = [self.robots[o].pose[:2] for o in team.robot_ids
              if o != r.robot_id and self.robots[o].alive]
        if not xy:
            return np.zeros((0, 2))
        from server.slam.geometry import inverse

        return transform_points(inverse(r.pose), np.array(xy))

    def planning_grid(self, team_id: str) -> PlanningGrid:
        """The team's occupancy grid in the nav2 convention (robots of one team share it)."""
        team = self.teams[team_id]
        grid = self.robots[team.robot_ids[0]].slam.occupancy_grid()
        return PlanningGrid(grid.to_nav2(), grid.resolution_m,
                            (float(grid.origin[0]), float(grid.origin[1])))

    @staticmethod
    def _explorer_params_from(cfg: ServerConfig) -> ExplorerParams:
        e, c = cfg.explore, cfg.control
        analysis = AnalysisParams(cost=CostParams(robot_radius_m=c.robot_radius_m,
                                                  unknown_is_obstacle=e.unknown_as_obstacle))
        return ExplorerParams(analysis=analysis, lam=e.lam, total_area_m2=e.total_area_m2,
                              coverage_threshold=e.coverage_threshold)

    # -- outputs ---------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        return bool(self.teams) and all(t.finished for t in self.teams.values())

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
