"""What the operator sees of a mission on a known map, and placing a robot in it by hand.

1. **Seen.** Each robot's localisation state (``searching``, ``placed``, ``lost``: searching
   again after it was lost) and, while it searches, the strongest placements of its team's
   latest query, as poses in the map's frame (``localisation``, read into the robot states the
   server publishes).
2. **Placed by hand.** When what a robot has seen does not tell places apart (rooms alike) or
   is too little, the operator says where it stands: a pose in the map's frame
   (``place_by_hand``, the order ``place``). That pose is a guess, never taken as it is:
   - the team's map is matched against the known map as a query would, but only against
     the part of it the robot's map would cover from there (give or take ``NEAR_M``), and
     keeping more candidates: in a building of rooms alike the global query's few best may all
     lie in other rooms than the one the operator means. The strongest placement that puts
     the robot within ``NEAR_M`` and ``NEAR_DEG`` of the operator's pose refines it (a press
     and a drag on a screen say roughly where, not to the centimetre);
   - without one, the operator's pose goes on as it is;
   - where other placements elsewhere fit the robot's map about as well (``clear_ratio``
     of the chosen one's strength: rooms alike), the order is refused, saying so, unless
     what the robot has seen tells the chosen one apart from them (its map contradicts
     each of them clearly more: ``tellapart.apart``, the rule a query uses); the robot is
     meanwhile sent where they differ (``tellapart``), and may be placed by hand after;
   - either way it then passes the merger's checks as any placement does
     (``KnownMapDesk.place``): the maps must not contradict each other and the robot's own
     keyframes must match the map where they overlap. A guess that fails them is refused,
     with the reason, and the robot goes on searching.

No I/O here.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas import Hypothesis
from schemas.se2 import compose, inverse, wrap_angle
from server.command.operator import Refused
from server.fleet.model import RobotContext
from server.knownmap import tellapart
from server.knownmap.desk import KnownMapDesk
from server.knownmap.ghosts import MAP_TEAM
from server.knownmap.placing import MapTarget, candidates, placements
from server.knownmap.search import Guess
from server.rendezvous.mapmatch import layers
from server.slam.grid import OccupancyGrid

F64 = NDArray[np.float64]

#: a placement refines the operator's pose when it puts the robot this close to it
NEAR_M, NEAR_DEG = 1.5, 30.0
#: candidates kept per square of the robot's map in that search (a query keeps fewer)
TOP_K = 12


def localisation(desk: KnownMapDesk) -> dict[str, dict[str, Any]]:
    """Per robot (not the map's ghosts): ``localisation`` and ``hypotheses`` as the robot
    states carry them."""
    return {d["robot_id"]: {"localisation": d["state"],
                            "hypotheses": [Hypothesis(pose=tuple(h["pose"]),
                                                      strength=float(h["strength"]))
                                           for h in d["hypotheses"]]}
            for d in desk.states()}


def place_by_hand(desk: KnownMapDesk, r: RobotContext, pose: tuple[float, float, float],
                  now_ns: int) -> str:
    """Place ``r`` (its team) with it at ``pose`` in the map's frame, refined and checked
    (the module docstring). Returns what was done; raises ``Refused`` with the reason."""
    if r.ghost:
        raise Refused(f"robot_id: {r.robot_id} holds part of the known map; it is no robot")
    if r.team_id == MAP_TEAM:
        raise Refused(f"robot_id: {r.robot_id} is already placed in the known map")
    fleet = desk.fleet
    team = fleet.team_of(r)
    if not any(fleet.robots[rid].slam.keyframes for rid in team.robot_ids):
        raise Refused(f"robot_id: {r.robot_id} has no map of its own yet to place")
    want = np.asarray(pose, float)
    T_hand = compose(want, inverse(r.pose))          # the team's frame -> the map's
    T, strength, how = T_hand, 0.0, "as given (its map fits the known map nowhere near)"
    near = nearby(desk, team.team_id, r.pose, want)
    if near is not None:
        T, strength = near
        at = compose(T, r.pose)
        how = (f"refined by the maps to ({at[0]:.2f}, {at[1]:.2f}, "
               f"{math.degrees(at[2]):.0f}°), {_off(at, want)}")
    alike = _alike(desk, team.team_id, r.pose, compose(T, r.pose), strength)
    if alike and not _told_apart(desk, team.team_id, T, alike):
        at = compose(alike[0], r.pose)
        raise Refused(f"pose: {how}, but {len(alike)} other place(s) fit its map as well, as "
                      f"at ({at[0]:.2f}, {at[1]:.2f}, {math.degrees(at[2]):.0f}°), and nothing "
                      "it has seen tells them apart yet (rooms alike): let it see more (it is "
                      "sent where they differ), then place it again")
    guess = Guess(T, now_ns, now_ns, strength, 0.0, wins=0)
    if not desk.place(team, guess, now_ns, kind="by_hand"):
        if guess.status == "refused":
            raise Refused(f"pose: {how}, then refused: {guess.reason}")
        raise Refused(f"pose: {how}, but too little of {r.robot_id}'s map overlaps the known "
                      "map to check it yet: let it see more, then place it again")
    desk.counts["by_hand"] += 1
    x, y, th = (float(v) for v in r.pose)
    told = (f" ({len(alike)} other place(s) fit its map about as well, but it has seen what "
            "tells them apart)") if alike else ""
    return f"{how}; placed at ({x:.2f}, {y:.2f}, {math.degrees(th):.0f}°){told}"


def _alike(desk: KnownMapDesk, team_id: str, pose_own: F64, at: F64, strength: float
           ) -> list[F64]:
    """The team's latest query's placements elsewhere (not near ``at``) that fit about as
    well (``clear_ratio`` of ``strength`` or more)."""
    s = desk.searches.get(team_id)
    if s is None or strength <= 0:
        return []
    out = []
    for T, other, _ in s.shown:
        p = compose(T, pose_own)
        if other >= desk.k.clear_ratio * strength and math.hypot(*(p[:2] - at[:2])) > NEAR_M:
            out.append(T)
    return out


def _told_apart(desk: KnownMapDesk, team_id: str, T: F64, others: list[F64]) -> bool:
    """The team's map contradicts each of ``others`` clearly more than ``T``
    (``tellapart.conflicts``, the rule a query uses)."""
    mine = layers(desk.fleet.team_grid(team_id), tellapart.CELL_M)
    args = (mine, tellapart.clear_layer(mine), *desk.open_floor())
    c = tellapart.conflicts(T, *args)
    return all(tellapart.apart(c, tellapart.conflicts(U, *args)) for U in others)


def nearby(desk: KnownMapDesk, team_id: str, pose_own: F64, want: F64
           ) -> tuple[F64, float] | None:
    """The strongest placement of the team's map on the known map that puts the robot (at
    ``pose_own`` in its team's frame) near ``want``: its transform and strength."""
    fleet = desk.fleet
    p = replace(desk.params, top_k=max(desk.params.top_k, TOP_K))
    team = fleet.teams[team_id]
    xy = np.concatenate([fleet.robots[rid].slam.keyframe_poses()[:, :2]
                         for rid in team.robot_ids if fleet.robots[rid].slam.keyframes])
    reach = max(fleet.robots[rid].sensor_range_m for rid in team.robot_ids)
    # where the robot's places would lie, were it where the operator says
    at = compose(want, inverse(pose_own))
    places = np.array([compose(at, np.array([x, y, 0.0]))[:2] for x, y in xy])
    target = MapTarget(_near_part(desk, places, reach + NEAR_M), p)
    for pl in placements(candidates(target, fleet.team_grid(team_id), xy, p), p):
        at = compose(pl.T_map_own, pose_own)
        if math.hypot(*(at[:2] - want[:2])) <= NEAR_M and \
                abs(math.degrees(wrap_angle(at[2] - want[2]))) <= NEAR_DEG:
            return pl.T_map_own, pl.strength
    return None


def _near_part(desk: KnownMapDesk, places_xy: F64, radius_m: float) -> OccupancyGrid:
    """The known map as its team draws it (kept up by its mapper as the map grows), with
    only its cells within ``radius_m`` of a place known."""
    grid = desk.fleet.team_grid(MAP_TEAM)
    h, w = grid.shape
    res = grid.resolution_m
    cx = grid.origin[0] + (np.arange(w) + 0.5) * res
    cy = grid.origin[1] + (np.arange(h) + 0.5) * res
    near = np.zeros((h, w), bool)
    for x, y in places_xy:
        near |= (cy[:, None] - y) ** 2 + (cx[None, :] - x) ** 2 <= radius_m ** 2
    return OccupancyGrid.from_dense(grid.params, (float(grid.origin[0]), float(grid.origin[1])),
                                    grid.log_odds, grid.observed & near)


def _off(at: F64, want: F64) -> str:
    return (f"{math.hypot(*(at[:2] - want[:2])):.2f} m and "
            f"{abs(math.degrees(wrap_angle(at[2] - want[2]))):.0f}° from the operator's pose")
