"""The known map's place among the fleet's robots: keyframes held by ghosts.

A ghost is a ``RobotContext`` that drives nothing and is never reported: it only holds
keyframes its team's map is drawn from, in the team's graph. The known map is one (``MAP_ID``,
in the team ``MAP_TEAM``, which it anchors); so, after a robot placed in the map is lost, is the
graph it had until then (its keyframes from before it was lost still map the building, those
made while it was lost are retired). The robot itself starts afresh in a team of its own,
as a newcomer does. Everything the merger, the graph surgery and the team map do with robots
then works for the map unchanged. No I/O here.
"""

from __future__ import annotations

import logging

import numpy as np

from server.fleet.model import Fleet, RobotContext, Team
from server.knownmap.mapdata import KnownMap, harvest, map_slam
from server.lookout import NullLookout

log = logging.getLogger(__name__)

#: the ghost holding the known map, and its team (a robot of that name is refused)
MAP_ID = "map"
MAP_TEAM = "known-map"


def add_map(fleet: Fleet, known: KnownMap) -> RobotContext:
    """The known map as the fleet's first team: a ghost holding its keyframes, anchoring
    the team's frame (the map's)."""
    char, block = fleet.key_space()
    slam = map_slam(known, fleet.stages.slam(char, block))
    g = RobotContext(MAP_ID, slam, fleet.stages.navigator(), MAP_TEAM, NullLookout(),
                     alive=False, ghost=True, start_checked=True)
    g.pose = slam.pose
    fleet.robots[MAP_ID] = g
    fleet.teams[MAP_TEAM] = Team(MAP_TEAM, [MAP_ID], fleet.stages.visited(), anchor=MAP_ID,
                                 mapper=fleet.stages.mapper(), known=True)
    log.info("known map: %d keyframes from %d mission(s), graph symbol %r", len(known),
             known.missions, char)
    return g


def detach(fleet: Fleet, r: RobotContext, kept: int, stamp_ns: int) -> str:
    """``r`` leaves its team (the known map's) and starts afresh in a team of its own: its
    graph stays in the team under a ghost, its first ``kept`` keyframes still drawn (those
    made since are retired). Returns the robot's new team."""
    team = fleet.team_of(r)
    n = sum(1 for rid in fleet.robots if rid.startswith(f"{r.robot_id}-lost"))
    gid = f"{r.robot_id}-lost{n + 1}"
    g = RobotContext(gid, r.slam, r.nav, team.team_id, NullLookout(), pose=r.pose.copy(),
                     alive=False, ghost=True, start_checked=True, unmapped=r.unmapped,
                     retired=set(r.retired) | set(range(kept, len(r.slam.keyframes))))
    fleet.robots[gid] = g
    team.robot_ids = [gid if rid == r.robot_id else rid for rid in team.robot_ids]
    for ln in team.links:
        ln.a = gid if ln.a == r.robot_id else ln.a
        ln.b = gid if ln.b == r.robot_id else ln.b
    if team.anchor == r.robot_id:
        team.anchor = gid
    char, block = fleet.key_space()
    k = 1
    while (new_team := f"team-{r.robot_id}-{k}") in fleet.teams or \
            new_team in fleet.retired_teams:
        k += 1
    r.slam = fleet.stages.slam(char, block)
    r.nav = fleet.stages.navigator()
    r.look.forget()
    r.team_id, r.unmapped, r.retired = new_team, False, set()
    r.pose, r.start_pose = np.zeros(3), np.zeros(3)
    r.meeting, r.sighted, r.obstacles = None, None, None
    fleet.teams[new_team] = Team(new_team, [r.robot_id], fleet.stages.visited(),
                                 anchor=r.robot_id, mapper=fleet.stages.mapper())
    fleet.coordinate(team)
    fleet.latest_grids.pop(new_team, None)
    log.info("robot %s left %s at %.1f s: its graph stays there as %s (%d keyframes kept)",
             r.robot_id, team.team_id, stamp_ns * 1e-9, gid, kept)
    return new_team


def team_map(fleet: Fleet, team_id: str, mission: int, sources: dict[str, list[str]],
             notes: dict[str, str] | None = None) -> KnownMap | None:
    """A team's map as a known map made by ``mission`` missions (what it draws: ghosts' and
    mapping robots' keyframes that are not retired), in the team's frame; None without
    keyframes. ``sources``: each keyframe's source, for graphs that hold a known map's
    (the others' are ``"<mission>:<robot>"``)."""
    team = fleet.teams[team_id]
    parts = []
    for rid in team.robot_ids:
        r = fleet.robots[rid]
        kfs, poses = r.mapped_keyframes()
        if not kfs:
            continue
        own = sources.get(rid)
        robot = rid.split("-lost")[0] if r.ghost else rid
        names = ([own[kf.index] for kf in kfs] if own is not None
                 else [f"{mission}:{robot}"] * len(kfs))
        parts.append((names, list(kfs), poses))
    if not parts:
        return None
    anchor = team.anchor.split("-lost")[0]
    return harvest(parts, fleet.cfg.slam.grid.resolution_m, anchor, mission, notes)


def largest_team(fleet: Fleet) -> str | None:
    """The team whose map holds the most keyframes (a mission's map, when no known map was
    loaded: its robots may not all have met)."""
    best = max(fleet.teams.values(), default=None,
               key=lambda t: (sum(len(fleet.robots[r].mapped_keyframes()[0])
                                  for r in t.robot_ids), t.team_id))
    return None if best is None else best.team_id
