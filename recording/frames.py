"""The frame tree a run draws in: team maps, each robot's odometry frame, each robot.

Frames (REP 105's map → odom → base_link, one chain per robot)::

    <team>  --T_team_odom-->  <robot>/odom  --odom_pose-->  <robot>

The server estimates ``T_team_robot`` about once a second (``RobotStates``), for the scan stamped
``last_scan_stamp_ns``; the robot's odometry comes with every scan. The correction
``T_team_odom = T_team_robot ∘ (T_odom_robot at that scan)⁻¹`` is held until the next estimate,
so every scan carries a full chain at its own stamp. A merge ties the joining team's frame under
the surviving one (``T_a_b``, the merge event's transform), so once the teams have met every
frame hangs from one root; an undone merge unties it again.

Pure bookkeeping: numpy and the project's SE(2) helpers, no I/O.
"""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from schemas import Event, RobotStates, Scan
from schemas.se2 import F64, compose, inverse

#: odometry poses kept per robot to find the one an estimate refers to (10 Hz: ~20 s)
ODOM_HISTORY = 200
#: trajectory poses kept per robot (server estimates, about one a second)
TRAJECTORY_LENGTH = 5000

_JOINED = re.compile(r"^(\S+) merged into ")
_SPLIT = re.compile(r"^(\S+) split from ")


def odom_frame(robot_id: str) -> str:
    return f"{robot_id}/odom"


@dataclass(frozen=True)
class Transform:
    """``parent`` → ``child``: the pose of the child frame in the parent, at ``stamp_ns``."""

    parent: str
    child: str
    pose: tuple[float, float, float]
    stamp_ns: int


@dataclass
class FrameTree:
    """What the run has said so far about how the frames relate."""

    team_of: dict[str, str] = field(default_factory=dict)          # robot -> team
    T_team_odom: dict[str, F64] = field(default_factory=dict)      # robot -> correction
    odom: dict[str, deque[tuple[int, F64]]] = field(default_factory=dict)  # robot -> history
    links: dict[str, tuple[str, F64]] = field(default_factory=dict)  # joined team -> (team, T)
    link_stamp_ns: dict[str, int] = field(default_factory=dict)  # joined team -> merge stamp
    trajectories: dict[str, list[F64]] = field(default_factory=dict)  # robot -> poses
    trajectory_frame: dict[str, str] = field(default_factory=dict)   # robot -> their team
    last_stamp_ns: dict[str, int] = field(default_factory=dict)    # robot -> last scan stamp

    # -- what arrives -------------------------------------------------------------------------
    def add_scan(self, scan: Scan) -> list[Transform]:
        """Remember the scan's odometry; the transforms that place it, at its stamp."""
        rid = scan.robot_id
        hist = self.odom.setdefault(rid, deque(maxlen=ODOM_HISTORY))
        hist.append((scan.stamp_ns, np.asarray(scan.odom_pose, dtype=np.float64)))
        self.last_stamp_ns[rid] = scan.stamp_ns
        return self.transforms(scan.stamp_ns)

    def add_states(self, states: RobotStates) -> list[Transform]:
        """New corrections from the server's estimates; appends to the trajectories."""
        for est in states.robots:
            rid, T_team_robot = est.robot_id, np.asarray(est.pose, dtype=np.float64)
            self.team_of[rid] = est.team_id
            self._move_trajectory(rid, est.team_id)
            odom = self._odom_at(rid, est.last_scan_stamp_ns)
            if odom is not None:
                self.T_team_odom[rid] = compose(T_team_robot, inverse(odom))
            traj = self.trajectories.setdefault(rid, [])
            traj.append(T_team_robot)
            del traj[:-TRAJECTORY_LENGTH]
        return self.transforms(states.stamp_ns)

    def add_event(self, ev: Event) -> list[Transform]:
        """A merge ties the joining team under the surviving one; an undo unties it."""
        if ev.kind == "merge" and ev.team_id and ev.transform is not None:
            joined = self._joined_team(ev)
            if joined and joined != ev.team_id and not self._under(ev.team_id, joined):
                self.links[joined] = (ev.team_id, np.asarray(ev.transform, dtype=np.float64))
                self.link_stamp_ns[joined] = ev.stamp_ns
                for rid, team in list(self.trajectory_frame.items()):
                    if team == joined:
                        self._move_trajectory(rid, ev.team_id)
        elif ev.kind == "merge_undone" and (m := _SPLIT.match(ev.message)):
            self.links.pop(m.group(1), None)
        return self.transforms(ev.stamp_ns)

    # -- what is drawn ------------------------------------------------------------------------
    def transforms(self, stamp_ns: int) -> list[Transform]:
        """Every transform known now: team links at their merge's stamp (they hold from then
        on), corrections at ``stamp_ns``, each robot's odometry at its own latest scan."""
        out = [Transform(parent, child, _pose(T), self.link_stamp_ns.get(child, stamp_ns))
               for child, (parent, T) in sorted(self.links.items())]
        for rid in sorted(self.odom):
            team, T = self.team_of.get(rid), self.T_team_odom.get(rid)
            if team is not None and T is not None:
                out.append(Transform(team, odom_frame(rid), _pose(T), stamp_ns))
            stamp, odom = self.odom[rid][-1]
            out.append(Transform(odom_frame(rid), rid, _pose(odom), stamp))
        return out

    # -- helpers ------------------------------------------------------------------------------
    def _odom_at(self, rid: str, stamp_ns: int) -> F64 | None:
        """The odometry of the scan stamped ``stamp_ns`` (else the nearest one kept)."""
        hist = self.odom.get(rid)
        if not hist:
            return None
        return min(hist, key=lambda h: abs(h[0] - stamp_ns))[1]

    def _joined_team(self, ev: Event) -> str | None:
        """The team that joined ``ev.team_id``: where its robots were before, else the text."""
        before = {self.team_of[r] for r in ev.robot_ids if r in self.team_of} - {ev.team_id}
        if len(before) == 1:
            return before.pop()
        m = _JOINED.match(ev.message)
        return m.group(1) if m else None

    def _under(self, frame: str, ancestor: str) -> bool:
        """Whether ``ancestor`` is above ``frame`` through the team links (a cycle guard)."""
        seen: set[str] = set()
        while frame in self.links and frame not in seen:
            seen.add(frame)
            frame = self.links[frame][0]
            if frame == ancestor:
                return True
        return False

    def _in_team(self, team: str, ancestor: str) -> F64 | None:
        """``T_ancestor_team`` along the team links, or None when they do not lead there."""
        T = np.zeros(3)
        seen: set[str] = set()
        while team != ancestor:
            if team not in self.links or team in seen:
                return None
            seen.add(team)
            team, T_parent_team = self.links[team]
            T = compose(T_parent_team, T)
        return T

    def _move_trajectory(self, rid: str, team: str) -> None:
        """Bring a robot's past poses into ``team``'s frame (dropped when no link says how)."""
        old = self.trajectory_frame.get(rid, team)
        self.trajectory_frame[rid] = team
        traj = self.trajectories.get(rid)
        if old == team or not traj:
            return
        T = self._in_team(old, team)
        if T is None:
            self.trajectories[rid] = []
            return
        self.trajectories[rid] = list(compose(T, np.asarray(traj)))


def _pose(T: F64) -> tuple[float, float, float]:
    return float(T[0]), float(T[1]), float(T[2])
