"""The operator's orders: stop and resume robots, send one to a point, bring robots home,
place a robot on a known map by hand.

Orders come from the console (``server.console``), go through the node's worker like
everything else the server accepts (journaled first, so a restarted server holds them again),
and are carried out here, inside the core, one thread:

1. ``parse`` checks a request's shape (action, robot, point) and raises ``OperatorError``
   naming the field; nothing reaches the core that fails it.
2. ``OperatorOrders.apply`` decides against the core's state (an unknown robot, a point with
   no path to it are refused, with the reason) and returns what happened in one line.
3. ``OperatorOrders.command`` is asked first for every robot's command: a held robot gets
   zero — before exploration, lookout turns and recovery manoeuvres are even asked — and a
   robot on an errand (a point, or its start once its team is done) follows the errand's path.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose
from server.control import Obstacles, PurePursuit, Twist
from server.exploration.analysis import analyse
from server.fleet.model import Fleet, RobotContext
from server.planning import PlanningError
from server.planning.astar import plan

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

ACTIONS = ("stop", "resume", "goto", "home", "place")
_ROBOT_ID = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
#: a point farther than this from the origin of a map is no point on it
MAX_COORD_M = 10_000.0


class OperatorError(ValueError):
    """A request that cannot be taken: malformed, or naming something that is not there."""

    #: how the console answers it (400: malformed; 404: unknown robot; 409: refused now)
    status = 400


class UnknownRobot(OperatorError):
    status = 404


class Refused(OperatorError):
    status = 409


@dataclass(frozen=True)
class OperatorCommand:
    """One order. ``robot_id`` None: every robot (stop, resume, home). ``point_xy``: goto's
    goal in the robot's team frame (the frame its team's map is drawn in). ``on``: home's
    switch (return home once the team is done, or not). ``pose``: place's pose of the robot
    in the known map's frame (x, y [m], θ [rad])."""

    action: str
    robot_id: str | None = None
    point_xy: tuple[float, float] | None = None
    on: bool = True
    pose: tuple[float, float, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        out = {"action": self.action, "robot_id": self.robot_id,
               "point": None if self.point_xy is None else list(self.point_xy), "on": self.on}
        if self.pose is not None:
            out["pose"] = list(self.pose)
        return out

    def describe(self) -> str:
        who = self.robot_id or "every robot"
        if self.action == "goto" and self.point_xy is not None:
            return f"send {who} to ({self.point_xy[0]:.2f}, {self.point_xy[1]:.2f})"
        if self.action == "home":
            return f"{who}: return home when done {'on' if self.on else 'off'}"
        if self.action == "place" and self.pose is not None:
            x, y, th = self.pose
            return f"place {who} by hand at ({x:.2f}, {y:.2f}, {math.degrees(th):.0f}°)"
        return f"{self.action} {who}"


def parse(data: Any) -> OperatorCommand:
    """An ``OperatorCommand`` from a decoded JSON request (or a journal record)."""
    if not isinstance(data, dict):
        raise OperatorError(f"a command is a JSON object, not {type(data).__name__}")
    unknown = set(data) - {"action", "robot_id", "point", "on", "pose"}
    if unknown:
        raise OperatorError(f"unknown field(s) {', '.join(sorted(map(str, unknown)))}")
    action = data.get("action")
    if action not in ACTIONS:
        raise OperatorError(f"action: {action!r} is none of {', '.join(ACTIONS)}")
    rid = data.get("robot_id")
    if rid is not None and not (isinstance(rid, str) and _ROBOT_ID.match(rid)):
        raise OperatorError(f"robot_id: {rid!r} is not a robot id ([A-Za-z0-9_-], 1-32)")
    on = data.get("on", True)
    if not isinstance(on, bool):
        raise OperatorError(f"on: {on!r} is not true or false")
    point = data.get("point")
    xy: tuple[float, float] | None = None
    if action == "goto":
        if rid is None:
            raise OperatorError("robot_id: goto sends one robot")
        if not (isinstance(point, list | tuple) and len(point) == 2
                and all(isinstance(v, int | float) and not isinstance(v, bool) for v in point)):
            raise OperatorError(f"point: {point!r} is not [x, y] in metres")
        xy = (float(point[0]), float(point[1]))
        if not all(math.isfinite(v) and abs(v) <= MAX_COORD_M for v in xy):
            raise OperatorError(f"point: {point!r} is not a finite point within "
                                f"{MAX_COORD_M:.0f} m")
    elif point is not None:
        raise OperatorError(f"point: only goto takes a point, not {action}")
    pose = _pose(action, rid, data.get("pose"))
    return OperatorCommand(action, rid, xy, on, pose)


def _pose(action: str, rid: str | None, pose: Any) -> tuple[float, float, float] | None:
    """place's pose: [x, y, θ], finite, the point within ``MAX_COORD_M``, θ within ±2π."""
    if action != "place":
        if pose is not None:
            raise OperatorError(f"pose: only place takes a pose, not {action}")
        return None
    if rid is None:
        raise OperatorError("robot_id: place places one robot")
    if not (isinstance(pose, list | tuple) and len(pose) == 3
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in pose)):
        raise OperatorError(f"pose: {pose!r} is not [x, y, θ] in metres and radians")
    x, y, th = (float(v) for v in pose)
    if not (all(math.isfinite(v) and abs(v) <= MAX_COORD_M for v in (x, y))
            and math.isfinite(th) and abs(th) <= 2 * math.pi):
        raise OperatorError(f"pose: {pose!r} is not a finite pose within {MAX_COORD_M:.0f} m "
                            "and ±2π")
    return x, y, th


@dataclass
class Errand:
    """A path the operator sent a robot along, in its team's frame at the time."""

    kind: str                      # goto | home | inspect (``server.knownmap``'s pass)
    team_id: str
    goal_xy: tuple[float, float]
    path_xy: F64
    pursuit: PurePursuit
    since_ns: int = 0              # when it was given (the server's own are given up after a while)
    #: the server's own: the nearest it has come to its goal [m], and when
    nearest_m: float = float("inf")
    nearest_ns: int = 0


@dataclass
class OperatorOrders:
    """What the operator ordered, as the core holds it (pickled with the core's state)."""

    stop_all: bool = False
    stopped: set[str] = field(default_factory=set)
    home_all: bool = False
    home: set[str] = field(default_factory=set)
    errands: dict[str, Errand] = field(default_factory=dict)
    #: robots that went home once their team was done (or could not: not asked again)
    homed: set[str] = field(default_factory=set)
    applied: int = 0
    refused: int = 0

    def holds(self, robot_id: str) -> bool:
        return self.stop_all or robot_id in self.stopped

    def wants_home(self, robot_id: str) -> bool:
        return self.home_all or robot_id in self.home

    def view(self) -> dict[str, Any]:
        """What the console shows (plain data, safe to hand to another thread)."""
        return {"stop_all": self.stop_all, "stopped": sorted(self.stopped),
                "home_all": self.home_all, "home": sorted(self.home),
                "errands": {rid: {"kind": e.kind, "goal": list(e.goal_xy)}
                            for rid, e in self.errands.items()},
                "applied": self.applied, "refused": self.refused}

    # -- orders ----------------------------------------------------------------------------
    def apply(self, cmd: OperatorCommand, fleet: Fleet,
              place: Callable[[RobotContext, tuple[float, float, float]], str] | None = None
              ) -> str:
        """Carry out ``cmd``; returns what was done. Raises ``OperatorError`` (an unknown
        robot, a point with no path to it, a resume that a stop-all overrides). ``place``:
        how a robot is placed by hand on the known map (None: there is none)."""
        try:
            done = self._apply(cmd, fleet, place)
        except OperatorError:
            self.refused += 1
            raise
        self.applied += 1
        return done

    def _apply(self, cmd: OperatorCommand, fleet: Fleet,
               place: Callable[[RobotContext, tuple[float, float, float]], str] | None) -> str:
        rid = cmd.robot_id
        r = None
        if rid is not None:
            r = fleet.robots.get(rid)
            if r is None:
                raise UnknownRobot(f"robot_id: no robot {rid} (known: "
                                   f"{', '.join(sorted(fleet.robots)) or 'none'})")
        if cmd.action == "stop":
            if r is None:
                self.stop_all = True
            else:
                self.stopped.add(r.robot_id)
            return f"{cmd.describe()}: held at zero velocity until resumed"
        if cmd.action == "resume":
            if r is None:
                held = self.stop_all or bool(self.stopped)
                self.stop_all = False
                resumed = list(fleet.robots.values())
                self.stopped.clear()
            else:
                if self.stop_all:
                    raise Refused(f"robot_id: {r.robot_id} is held by stop-all; resume all")
                held = r.robot_id in self.stopped
                self.stopped.discard(r.robot_id)
                resumed = [r]
            for q in resumed:   # the time held is no lack of progress
                q.nav.stuck.reset()
                q.look.reset()
            return f"{cmd.describe()}{'' if held else ' (it was not held)'}"
        if cmd.action == "home":
            if r is None:
                self.home_all = cmd.on
                if not cmd.on:
                    self.home.clear()
            elif cmd.on:
                self.home.add(r.robot_id)
            else:
                self.home.discard(r.robot_id)
            return cmd.describe()
        if cmd.action == "place":
            assert r is not None and cmd.pose is not None
            if place is None:
                raise Refused(f"robot_id: no known map to place {r.robot_id} on (the server "
                              "started without --map)")
            return f"{cmd.describe()}: {place(r, cmd.pose)}"
        assert cmd.action == "goto" and r is not None and cmd.point_xy is not None
        self.errands[r.robot_id] = self._errand(r, fleet, "goto", cmd.point_xy)
        return (f"{cmd.describe()}: path of "
                f"{len(self.errands[r.robot_id].path_xy)} points planned")

    def send(self, r: RobotContext, fleet: Fleet, kind: str, goal_xy: tuple[float, float],
             stamp_ns: int) -> None:
        """``r`` sent to ``goal_xy`` by the server itself; raises OperatorError (no way)."""
        self.errands[r.robot_id] = self._errand(r, fleet, kind, goal_xy)
        self.errands[r.robot_id].since_ns = stamp_ns

    def _errand(self, r: RobotContext, fleet: Fleet, kind: str,
                goal_xy: tuple[float, float]) -> Errand:
        """A planned path from where ``r`` is to ``goal_xy`` over its team's map."""
        grid = fleet.latest_grids.get(r.team_id)
        if grid is None or not r.scans:
            raise Refused(f"robot_id: {r.robot_id} has no map yet")
        pose_xy = (float(r.pose[0]), float(r.pose[1]))
        params = r.nav.own_explorer.params.analysis
        try:
            analysis = analyse(grid, params, include_xy=np.array([pose_xy]))
            path = plan(analysis.layer, pose_xy, goal_xy)
        except PlanningError as e:
            raise Refused(f"point: no way for {r.robot_id} to ({goal_xy[0]:.2f}, "
                          f"{goal_xy[1]:.2f}): {e}") from e
        pursuit = PurePursuit(r.nav.pursuit.params)
        return Errand(kind, r.team_id, goal_xy, path.xy_m, pursuit)

    # -- commands --------------------------------------------------------------------------
    def command(self, r: RobotContext, fleet: Fleet, obstacles: Obstacles,
                events: Any, stamp_ns: int) -> Twist | None:
        """Zero for a held robot; the errand's command for a robot on one; None: the robot
        is the navigator's (and the lookout's)."""
        if self.holds(r.robot_id):
            return Twist(0.0, 0.0)
        team = fleet.team_of(r)
        if (team.finished and self.wants_home(r.robot_id) and r.robot_id not in self.homed
                and r.robot_id not in self.errands):
            self.homed.add(r.robot_id)
            try:
                self.errands[r.robot_id] = self._errand(r, fleet, "home", home_xy(r))
                msg = f"{r.robot_id} returns to its start (its team is done)"
            except OperatorError as e:
                msg = f"{r.robot_id} cannot return to its start: {e}"
            events.emit("operator", [r.robot_id], r.team_id, msg, stamp_ns)
        errand = self.errands.get(r.robot_id)
        if errand is None:
            return None
        if errand.team_id != r.team_id:
            del self.errands[r.robot_id]
            events.emit("operator", [r.robot_id], r.team_id,
                        f"{r.robot_id}'s {errand.kind} errand dropped: its map frame changed "
                        f"(team {errand.team_id} -> {r.team_id})", stamp_ns)
            return None
        drive = r.nav.driver.follow(errand.pursuit, r.pose, errand.path_xy, obstacles)
        if drive.reached:
            del self.errands[r.robot_id]
            x, y = errand.goal_xy
            events.emit("operator", [r.robot_id], r.team_id,
                        f"{r.robot_id} reached ({x:.2f}, {y:.2f}) ({errand.kind})", stamp_ns)
            r.nav.drop_target()         # explore afresh from here (a done robot stays done)
        return drive.twist


def home_xy(r: RobotContext) -> tuple[float, float]:
    """Where ``r`` started, in its team's frame now."""
    first = r.online.values[0] if len(r.online) else np.zeros(3)
    p = compose(r.own_frame_in_team(), first) if r.slam.keyframes else r.start_pose
    return float(p[0]), float(p[1])
