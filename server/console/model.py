"""What the console page shows, built from the server's own outputs on the bus.

The server publishes team maps, robot states and events (``docs/wire.md``); the model keeps
what a page needs of them — each team's latest map (its cells still zlib-compressed: the
browser inflates them), every robot's state and trail, each team's coverage against time, the
last events — and turns each message into a frame for the pages already open. A page that
connects later gets ``snapshot()``. Per-robot health comes from the node's counters, read once
a second: scans accepted (their rate, and when the count last moved) and dropped. No I/O, one
thread.
"""

from __future__ import annotations

import base64
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from schemas import Event, MapUpdate, RobotStates

#: per robot, trail points kept (older halves are thinned out beyond this)
MAX_TRAIL = 4000
#: per team, coverage points kept (thinned out the same way)
MAX_COVERAGE = 2000
#: events a new page is shown
MAX_EVENTS = 300
#: a trail point is added when the robot moved this far [m]
TRAIL_STEP_M = 0.05
#: scans counted over this window for the rate [s]
RATE_WINDOW_S = 5.0


@dataclass(frozen=True)
class Frame:
    """One message to the pages: ``kind`` (the SSE event name) and its JSON-ready data.
    ``slot``: frames with the same slot replace each other in a slow page's queue (only the
    newest map of a team matters); None: each is kept (events)."""

    kind: str
    data: dict[str, Any]
    slot: str | None = None


@dataclass
class RobotHealth:
    #: (wall time, scans accepted so far), one a second over the rate's window
    counts: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=64))
    scans: int = 0
    last_seen: float = 0.0          # wall time its count was last seen to move


def _thin(points: list[Any], cap: int) -> None:
    """Keep every other point of the older half once ``cap`` is passed."""
    if len(points) > cap:
        half = len(points) // 2
        points[:half] = points[:half:2]


class ConsoleModel:
    """The page's model (one thread: the console's)."""

    def __init__(self) -> None:
        self.maps: dict[str, dict[str, Any]] = {}
        self.robots: dict[str, dict[str, Any]] = {}
        self.teams: dict[str, dict[str, Any]] = {}
        self.trails: dict[str, list[list[float]]] = {}
        self._trail_team: dict[str, str] = {}
        self.coverage: dict[str, list[list[float]]] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=MAX_EVENTS)
        self.health: dict[str, RobotHealth] = {}
        self.stamp_s = 0.0

    # -- inputs ----------------------------------------------------------------------------
    def on_map(self, msg: MapUpdate, seen_wall: float) -> Frame:
        data = {"team_id": msg.team_id, "robot_ids": list(msg.robot_ids),
                "width": msg.width, "height": msg.height, "resolution_m": msg.resolution_m,
                "origin": list(msg.origin), "stamp_s": msg.stamp_ns * 1e-9,
                "cells_zlib_b64": base64.b64encode(msg.cells).decode("ascii"),
                "seen_wall_ms": seen_wall * 1e3}
        self.maps[msg.team_id] = data
        return Frame("map", data, slot=f"map:{msg.team_id}")

    def on_robots(self, msg: RobotStates, seen_wall: float) -> Frame:
        t_s = msg.stamp_ns * 1e-9
        self.stamp_s = t_s
        live_teams = {t.team_id for t in msg.teams}
        for team_id in list(self.maps):         # a team merged into another has no map now
            if team_id not in live_teams:
                del self.maps[team_id]
        self.teams = {t.team_id: {"team_id": t.team_id, "robot_ids": list(t.robot_ids),
                                  "coverage": t.coverage, "explored_m2": t.explored_m2}
                      for t in msg.teams}
        for t in msg.teams:
            series = self.coverage.setdefault(t.team_id, [])
            if not series or t_s - series[-1][0] >= 1.0 or t.coverage != series[-1][1]:
                series.append([round(t_s, 2), round(t.coverage, 4)])
                _thin(series, MAX_COVERAGE)
        for r in msg.robots:
            x, y, th = r.pose
            self.robots[r.robot_id] = {
                "robot_id": r.robot_id, "team_id": r.team_id, "pose": [x, y, th],
                "sigma": list(r.pose_sigma), "mode": r.mode, "localisation": r.localisation,
                "target": None if r.target is None else list(r.target),
                "distance_m": r.distance_m, "keyframes": r.keyframes,
                "last_scan_s": r.last_scan_stamp_ns * 1e-9}
            trail = self.trails.setdefault(r.robot_id, [])
            if self._trail_team.get(r.robot_id) != r.team_id:
                trail.clear()      # a merge moved the robot into another frame
                self._trail_team[r.robot_id] = r.team_id
            if not trail or math.hypot(x - trail[-1][0], y - trail[-1][1]) >= TRAIL_STEP_M:
                trail.append([round(x, 3), round(y, 3)])
                _thin(trail, MAX_TRAIL)
        return Frame("robots", {"stamp_s": t_s, "robots": list(self.robots.values()),
                                "teams": list(self.teams.values()),
                                "seen_wall_ms": seen_wall * 1e3}, slot="robots")

    def on_event(self, msg: Event) -> Frame:
        data = {"seq": msg.seq, "kind": msg.kind, "stamp_s": msg.stamp_ns * 1e-9,
                "robot_ids": list(msg.robot_ids), "team_id": msg.team_id,
                "message": msg.message}
        self.events.append(data)
        return Frame("event", data)

    def on_counts(self, scans: dict[str, int], now_wall: float) -> None:
        """The node's count of scans accepted per robot, as of ``now_wall``."""
        for rid, n in scans.items():
            h = self.health.get(rid)
            if h is None:
                h = self.health[rid] = RobotHealth()
            if n != h.scans:
                h.scans, h.last_seen = n, now_wall
            h.counts.append((now_wall, n))
            while len(h.counts) > 2 and now_wall - h.counts[1][0] >= RATE_WINDOW_S:
                h.counts.popleft()

    # -- outputs ---------------------------------------------------------------------------
    def health_frame(self, dropped: dict[str, int], orders: dict[str, Any],
                     counters: dict[str, int], now_wall: float | None = None,
                     state: dict[str, Any] | None = None) -> Frame:
        """Per robot its scans (rate, last seen) and dropped ones, the operator's orders, the
        console's counters, and whether the server's state is being written
        (``server.runtime.keeper``)."""
        now = time.time() if now_wall is None else now_wall
        rows = {}
        for rid in sorted(set(self.health) | set(self.robots)):
            h = self.health.get(rid, RobotHealth())
            rate = 0.0
            if len(h.counts) > 1:
                (t0, n0), (t1, n1) = h.counts[0], h.counts[-1]
                rate = (n1 - n0) / (t1 - t0) if t1 > t0 else 0.0
            rows[rid] = {"scans": h.scans, "scan_rate_hz": round(rate, 2),
                         "dropped_scans": int(dropped.get(rid, 0)),
                         "last_seen_s_ago": (round(now - h.last_seen, 2) if h.last_seen
                                             else None)}
        return Frame("health", {"robots": rows, "orders": orders, "console": counters,
                                "state": state}, slot="health")

    def snapshot(self, health: Frame) -> Frame:
        """Everything a page that connects now needs to draw the run so far."""
        return Frame("snapshot", {"maps": list(self.maps.values()),
                                  "robots": list(self.robots.values()),
                                  "teams": list(self.teams.values()),
                                  "trails": self.trails, "coverage": self.coverage,
                                  "events": list(self.events), "health": health.data,
                                  "stamp_s": self.stamp_s})
