"""A robot's velocity command: the operator's first (a held robot stands, whatever else
would move it; a robot on an errand follows it), then its lookout while it turns toward (or
drives to) something that moves, a planned meeting, a turning camera's stop, its navigator
otherwise. Every detour from its own exploration (what the lookout starts, a camera's stop)
is priced first and taken only when worth its time (``server.fleet.detours``)."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor

import numpy as np
from numpy.typing import NDArray

from schemas import VelocityCommand
from schemas.se2 import inverse, transform_points
from server.command.operator import OperatorOrders
from server.config import ServerConfig
from server.control import ObstacleMemory, Obstacles, Twist
from server.exploration.navigator import NavMode
from server.fleet.events import EventLog
from server.fleet.model import Fleet, RobotContext
from server.lookout.offers import Offer
from server.planning import OccupancyGrid as PlanningGrid
from server.slam.scan import field_of_view

#: a scan spanning this much sees all round (a 360-beam LIDAR's span is 2π) [rad]
ALL_ROUND_RAD = 0.97 * 2 * np.pi

F64 = NDArray[np.float64]


def sight_range_m(r: RobotContext) -> float:
    """How far the robot's latest scan would have shown another robot, whatever its
    direction: its sensor's range for a scan that spans all round, else 0 (a narrow sensor,
    or a LIDAR with a blind sector, cannot say that nobody stands at some distance)."""
    v = r.view
    if v is None or field_of_view(v.angles)[0] < ALL_ROUND_RAD:
        return 0.0
    return r.sensor_range_m


def mapped_obstacles(grid: PlanningGrid | None, pose: F64, radius_m: float) -> F64:
    """The occupied cells of ``grid`` within ``radius_m`` of the robot at ``pose``, as points
    in its body frame (their centres); none without a grid."""
    if grid is None or radius_m <= 0:
        return np.zeros((0, 2))
    geo = grid.geometry
    (r0, c0), (r1, c1) = geo.world_to_cell(pose[:2] - radius_m), geo.world_to_cell(
        pose[:2] + radius_m)
    r0, c0 = max(int(r0), 0), max(int(c0), 0)
    r1, c1 = min(int(r1) + 1, geo.shape[0]), min(int(c1) + 1, geo.shape[1])
    if r0 >= r1 or c0 >= c1:
        return np.zeros((0, 2))
    rows, cols = np.nonzero(grid.occupied[r0:r1, c0:c1])
    xy = geo.cell_to_world(np.stack([rows + r0, cols + c0], axis=1))
    return transform_points(inverse(pose), xy[np.hypot(*(xy - pose[:2]).T) <= radius_m])


class Steering:
    """Commands for the fleet's robots (one thread)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, orders: OperatorOrders,
                 events: EventLog) -> None:
        self.cfg, self.fleet, self.orders, self.events = cfg, fleet, orders, events
        #: where navigators replan while their robots drive on (``ServerCore.use_pools``;
        #: None: on the scan's path)
        self.planner: Callable[[], Executor | None] | None = None
        #: robots standing still for a stop of their turning camera that was priced
        self.sweeping: set[str] = set()

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "planner": None}   # processes are not state

    def command(self, r: RobotContext, stamp_ns: int, ranges: F64, angles: F64,
                navigate: bool = True) -> VelocityCommand:
        """The command for ``r``'s scan at ``stamp_ns`` (zero when not ``navigate``)."""
        twist = Twist(0.0, 0.0)
        self.fleet.detours.tick(stamp_ns)
        if navigate:
            ok = np.isfinite(ranges)
            pts = np.stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])],
                           1)
            if r.slam.narrow and self.cfg.control.obstacle_memory_s > 0:   # its latest scan
                if r.obstacles is None:
                    r.obstacles = ObstacleMemory()
                pts = r.obstacles.around(stamp_ns, r.pose, pts,
                                         self.cfg.control.obstacle_memory_s)
            if r.slam.narrow:    # and what its team mapped right around it
                pts = np.concatenate([pts, mapped_obstacles(
                    self.fleet.latest_grids.get(r.team_id), r.pose,
                    self.cfg.control.mapped_obstacles_m)])
            # one set of obstacles for whatever drives the robot (``Driver``)
            obstacles = Obstacles(pts, self.fleet.others_in_robot_frame(r))
            ordered = self.orders.command(r, self.fleet, obstacles, self.events, stamp_ns)
            look = None if ordered is not None else self.look(r, stamp_ns * 1e-9, obstacles)
            if ordered is not None:
                twist = ordered
            elif look is not None:
                twist = look
            elif r.meeting is not None:
                twist = self.meet(r, obstacles, stamp_ns)
            elif self.sweep_stop(r, stamp_ns):
                twist = Twist(0.0, 0.0)   # still, while its turning camera looks round once
            else:
                team = self.fleet.team_of(r)
                twist = r.nav.step(stamp_ns * 1e-9, r.pose, r.start_pose, obstacles,
                                   lambda: self.fleet.planning_grid(team.team_id),
                                   team.visited,
                                   planner=None if self.planner is None else self.planner())
        return VelocityCommand(robot_id=r.robot_id, seq=r.scans, stamp_ns=stamp_ns,
                               v_mps=twist.v_mps, omega_rps=twist.omega_rps,
                               ttl_s=self.cfg.control.command_ttl_s)

    def meet(self, r: RobotContext, obstacles: Obstacles, stamp_ns: int = 0) -> Twist:
        """Drive to a planned meeting's place, then wait there (the lookout turns toward the
        other robot when it comes; see ``server.rendezvous.matchdesk``)."""
        m = r.meeting
        assert m is not None
        if m.path_xy is None or len(m.path_xy) == 0:
            return Twist(0.0, 0.0)
        drive = r.nav.driver.follow(r.nav.pursuit, r.pose, m.path_xy, obstacles)
        if drive.reached:
            m.path_xy = None
            m.arrived_ns = stamp_ns or r.last_stamp_ns
        return drive.twist

    def sweep_stop(self, r: RobotContext, stamp_ns: int) -> bool:
        """Whether the robot stands still for its turning camera now: when its sensor asks for
        a stop, the stop is priced once; not worth it, the robot drives on."""
        if r.nav.mode == NavMode.RECOVERING or not r.slam.sweep_due(stamp_ns):
            self.sweeping.discard(r.robot_id)
            return False
        if r.robot_id in self.sweeping:
            return True
        if self.fleet.detours.sweep(r, stamp_ns):
            self.sweeping.add(r.robot_id)
            return True
        r.slam.skip_sweep()
        return False

    def look(self, r: RobotContext, now_s: float, obstacles: Obstacles) -> Twist | None:
        """Turn toward something that moves while robots outside the team remain. A robot
        whose team is done keeps doing so: a robot still alone must be able to join it."""
        if not self.fleet.stages.looks or r.nav.mode == NavMode.RECOVERING:
            r.look.reset()
            return None
        if len(self.fleet.teams) < 2 and not r.look.active:
            return None
        if self.fleet.others_paused(r, r.last_stamp_ns):
            # every other team is one whose merge the maps keep refusing: nobody to seek
            if r.look.active:
                r.look.reset()
                r.nav.drop_target()
            return None
        if r.look.call is not None:     # only a call's answer asks how far it sees
            r.look.sensor_range_m = sight_range_m(r)
        twist = r.look.step(now_s, r.pose, obstacles.points_xy,
                            self.fleet.latest_grids.get(r.team_id),
                            self.fleet.mates_xy(r, alive_only=False))
        offer = r.look.offers.pending
        if offer is not None and not self.worth(r, offer, now_s):
            r.look.decline(now_s, now_s + self.cfg.detours.recheck_s)
            return None
        if twist is None:
            if r.look.moved:  # the approach took the robot off its path: decide afresh
                r.look.moved = False
                r.nav.drop_target()
            return None
        return r.nav.driver.avoid(twist, r.look.heading_error, obstacles)

    def worth(self, r: RobotContext, offer: Offer, now_s: float) -> bool:
        """Price what the lookout just started (``server.lookout.offers``); taken, the lookout
        goes on with the same robot without a new price for as long as it was priced for."""
        distance = float(np.hypot(*(offer.xy - r.pose[:2])))
        stamp_ns = int(now_s * 1e9)
        if offer.kind == "call":
            taken = self.fleet.detours.call(r, offer.caller, distance, stamp_ns)
        else:
            taken = self.fleet.detours.seek(r, distance, stamp_ns)
        if taken:
            d = self.cfg.detours
            r.look.offers.grant(offer, now_s + distance / self.cfg.control.v_mps + d.hold_s
                                + self.cfg.teams.max_pending_s)
        return taken
