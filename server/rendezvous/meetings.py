"""Meetings planned on a map-matched transform (``server.rendezvous.matchdesk``): one robot
of each team driven to one place of the overlap their maps agree on, and the meeting settled
when the tags merge the teams there (confirmed), under another transform or not in time
(refuted), or when a robot goes silent or another merge moves the frame (pending again).
Each takes the desk it works for."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import inverse, transform_points
from server.fleet.model import Meeting, MergeRecord, RobotContext
from server.planning import plan
from server.planning.costmap import CostLayer, build_cost_layer
from server.planning.errors import PlanningError
from server.rendezvous.mapmatch import Hypothesis, same_transform

if TYPE_CHECKING:
    from server.rendezvous.matchdesk import HypothesisEntry, MapMatchDesk

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

#: both robots of a meeting at their places this long without a merge refute it [s]: each
#: robot's lookout has turned toward where the other should stand by then
MEET_SEEN_S = 15.0


def arrange(desk: MapMatchDesk, e: HypothesisEntry, h: Hypothesis, now_ns: int,
            finishing: bool = False) -> None:
    """One robot of each team to one place of the overlap, if some pair of them can get
    there within ``teams.meet_max_detour_m`` (the farther of the two paths) and the meeting
    is worth their time (``server.fleet.detours``). ``finishing``: the two maps joined under
    the transform would cover the threshold; the robots have nothing left to explore that
    the merge would not give them, so any distance is worth driving, and the meeting has
    the time its paths take."""
    fleet, t = desk.fleet, desk.cfg.teams
    reach_m = math.inf if finishing else t.meet_max_detour_m
    if e.status != "pending":
        return      # refuted, refused, merged, or already being met
    if fleet.seeking_paused(e.team_a, e.team_b, now_ns):
        return      # their maps keep refusing a merge (see Fleet.seeking_paused)
    busy = any(fleet.robots[r].meeting is not None
               for tm in (e.team_a, e.team_b) for r in fleet.teams[tm].robot_ids)
    if busy:
        return
    side_a = [fleet.robots[r] for r in fleet.teams[e.team_a].robot_ids
              if fleet.robots[r].alive]
    side_b = [fleet.robots[r] for r in fleet.teams[e.team_b].robot_ids
              if fleet.robots[r].alive]
    layer_a, layer_b = _layer(desk, side_a[0]), _layer(desk, side_b[0])
    if not finishing:
        # the places where the maps agree, as they are: where one robot cannot get to its
        # place on its own map (the other map's unknown, a wall's margin), the transform is
        # not worth the trip yet. Moved onto floor both maps know, they made meetings on
        # wrong transforms in a floor of offices alike (office-3 2.02x -> 1.83x)
        places = [(c.centre_a, transform_points(inverse(e.T_ab), c.centre_a[None, :])[0])
                  for c in h.members]
    else:
        # each place moved to where both maps have free floor: a place cut from one map can
        # lie in the other's unknown, or in a wall's margin (the transform is good to
        # decimetres)
        found = [_common_place(layer_a, layer_b, e.T_ab, c.centre_a) for c in h.members]
        places = [f for f in found if f is not None]
        if not places:
            # none near the submaps' centres: the free floor of both maps nearest each pair
            # of robots (under a right transform they meet wherever both maps know the floor)
            places = _overlap_places(layer_a, layer_b, e.T_ab, [
                (ra.pose[:2], rb.pose[:2]) for ra in side_a for rb in side_b])
    best: tuple[float, RobotContext, RobotContext, F64, F64, F64, F64] | None = None
    tries = sorted(((max(math.hypot(*(ra.pose[:2] - p)),
                         math.hypot(*(rb.pose[:2] - p_b))),
                     i, j, k) for i, ra in enumerate(side_a) for j, rb in enumerate(side_b)
                    for k, (p, p_b) in enumerate(places)), key=lambda x: x[0])
    why: list[str] = [] if places else ["no floor is free on both maps"]
    for straight, i, j, k in tries[:6]:
        if straight > reach_m:
            break
        ra, rb, (p, p_b) = side_a[i], side_b[j], places[k]
        path_a, path_b = _path(layer_a, ra, p, why), _path(layer_b, rb, p_b, why)
        if path_a is None or path_b is None:
            continue
        cost = max(_length(path_a), _length(path_b))
        if cost <= 1.5 * reach_m and (best is None or cost < best[0]):
            best = (cost, ra, rb, p, p_b, path_a, path_b)
    if best is None:
        if e.seen == 1 or finishing:
            log.info("no meeting on T %s: %s", e.T_ab.round(2),
                     f"the nearest robots are {tries[0][0]:.1f} m from a place (at most "
                     f"{reach_m:.0f} m)" if tries and tries[0][0] > reach_m else
                     "no path of both robots within reach (" + "; ".join(why[:3]) + ")")
        return
    _, ra, rb, p, p_b, path_a, path_b = best
    # worth the two robots' time? (server.fleet.detours; not asked again soon if not) The
    # transforms the two maps fit under, not refuted, share the chance that one is right
    pair = {e.team_a, e.team_b}
    transforms = sum(1 for x in desk.log if {x.team_a, x.team_b} == pair
                     and x.status in ("pending", "meeting"))
    if fleet.detours.recently_declined(ra, "meeting", rb.robot_id, now_ns) or \
            not fleet.detours.meeting(ra, rb, _length(path_a), _length(path_b), now_ns,
                                      transforms):
        return
    cost, v = best[0], ra.nav.pursuit.params.v_mps
    until = now_ns * 1e-9 + min(math.inf if finishing else t.meet_timeout_s,
                                1.5 * cost / max(v, 0.05) + 30.0)
    idx = desk.log.index(e)
    ra.meeting = Meeting("go", rb.robot_id, idx, until, p, path_a, ra.team_id)
    rb.meeting = Meeting("go", ra.robot_id, idx, until, p_b, path_b, rb.team_id)
    e.status = "meeting"
    desk.counters.meetings += 1
    msg = (f"meeting planned: {ra.robot_id} and {rb.robot_id} to one place "
           f"({e.support} places of the maps agree on where it is)")
    log.info("%s; %s at %s, %s at %s", msg, ra.robot_id, p.round(2), rb.robot_id,
             p_b.round(2))
    desk.events.emit("meeting", [ra.robot_id, rb.robot_id], e.team_a, msg, now_ns)


#: a meeting's place moves to the nearest cell free on both teams' maps within this [m]
PLACE_SEARCH_M = 3.0
#: ... preferring cells this clear of walls on both maps [m]
PLACE_CLEARANCE_M = 0.5


def _layer(desk: MapMatchDesk, r: RobotContext) -> CostLayer:
    """The cost layer of the robot's team's map, as the robot plans on it."""
    return build_cost_layer(desk.fleet.planning_grid(r.team_id),
                            r.nav.own_explorer.params.analysis.cost)


def _common_place(layer_a: CostLayer, layer_b: CostLayer, T_ab: F64, p: F64
                  ) -> tuple[F64, F64] | None:
    """The cell nearest ``p`` (team a's frame) that both maps let a robot stand on, within
    ``PLACE_SEARCH_M``, those ``PLACE_CLEARANCE_M`` clear of walls on both first: its
    centre in a's frame and in b's. None when there is none."""
    geo = layer_a.geometry
    k = math.ceil(PLACE_SEARCH_M / geo.resolution_m)
    r, c = (int(v) for v in geo.world_to_cell(p))
    H, W = layer_a.cost.shape
    r0, r1, c0, c1 = max(0, r - k), min(H, r + k + 1), max(0, c - k), min(W, c + k + 1)
    if r0 >= r1 or c0 >= c1:
        return None
    rr, cc = np.nonzero(np.isfinite(layer_a.cost[r0:r1, c0:c1]))
    rr, cc = rr + r0, cc + c0
    xy_a = geo.cell_to_world(np.stack([rr, cc], axis=1))
    d = np.hypot(*(xy_a - p).T)
    xy_b = transform_points(inverse(T_ab), xy_a)
    rc_b = layer_b.geometry.world_to_cell(xy_b)
    ok = (d <= PLACE_SEARCH_M) & layer_b.geometry.contains(rc_b)
    ok[ok] = np.isfinite(layer_b.cost[rc_b[ok, 0], rc_b[ok, 1]])
    if not ok.any():
        return None
    idx = np.flatnonzero(ok)
    clear = np.minimum(layer_a.clearance_m[rr[idx], cc[idx]],
                       layer_b.clearance_m[rc_b[idx, 0], rc_b[idx, 1]])
    best = idx[np.lexsort((d[idx], clear < PLACE_CLEARANCE_M))[0]]
    return xy_a[best], xy_b[best]


#: the overlap's free floor is searched at this spacing [m]
OVERLAP_STEP_M = 0.5


def _overlap_places(layer_a: CostLayer, layer_b: CostLayer, T_ab: F64,
                    pairs: list[tuple[F64, F64]]) -> list[tuple[F64, F64]]:
    """For each pair of robots (a's position in a's frame, b's in b's), the cell that both
    maps let a robot stand on, ``PLACE_CLEARANCE_M`` clear of walls on both, nearest to the
    farther of the two (straight lines): its centre in a's frame and in b's."""
    geo = layer_a.geometry
    step = max(1, round(OVERLAP_STEP_M / geo.resolution_m))
    sub = layer_a.clearance_m[::step, ::step] >= PLACE_CLEARANCE_M
    sub &= np.isfinite(layer_a.cost[::step, ::step])
    rc = np.argwhere(sub) * step
    if not len(rc):
        return []
    xy_a = geo.cell_to_world(rc)
    xy_b = transform_points(inverse(T_ab), xy_a)
    rc_b = layer_b.geometry.world_to_cell(xy_b)
    ok = layer_b.geometry.contains(rc_b)
    ok[ok] = np.isfinite(layer_b.cost[rc_b[ok, 0], rc_b[ok, 1]]) & \
        (layer_b.clearance_m[rc_b[ok, 0], rc_b[ok, 1]] >= PLACE_CLEARANCE_M)
    if not ok.any():
        return []
    xy_a, xy_b = xy_a[ok], xy_b[ok]
    out: list[tuple[F64, F64]] = []
    for pa, pb in pairs:
        k = int(np.argmin(np.maximum(np.hypot(*(xy_a - pa).T), np.hypot(*(xy_b - pb).T))))
        if not any(np.array_equal(xy_a[k], q) for q, _ in out):
            out.append((xy_a[k], xy_b[k]))
    return out


def _path(layer: CostLayer, r: RobotContext, goal: F64, why: list[str] | None = None
          ) -> F64 | None:
    """The robot's path to ``goal`` on its team's map (``layer``), or None (the reason
    appended to ``why``)."""
    try:
        return plan(layer, r.pose[:2], goal, timeout_s=0.5).xy_m
    except PlanningError as e:
        if why is not None:
            why.append(f"{r.robot_id}: {e}")
        return None


def follow(desk: MapMatchDesk, now_ns: int) -> None:
    """Settle meetings: merged (confirmed), out of time (refuted), a robot gone."""
    fleet = desk.fleet
    for r in fleet.robots.values():
        m = r.meeting
        if m is None:
            continue
        e = desk.log[m.hypothesis] if 0 <= m.hypothesis < len(desk.log) else None
        other = fleet.robots.get(m.other)
        if e is None or other is None:
            stop(r)
            continue
        if other.team_id == r.team_id:
            rec = fleet.merges[-1] if fleet.merges else None
            if rec is not None and _agrees(desk, e, rec):
                if rec.kind == "tags":
                    rec.kind = "meeting"
                settle(desk, e, "confirmed", "the tags merged the teams at the meeting",
                             now_ns)
            else:
                settle(desk, e, "refuted", "the teams merged under another transform",
                             now_ns)
        elif not (r.alive and other.alive):
            settle(desk, e, "pending", "a robot of the meeting went silent", now_ns)
        elif r.team_id != m.team_id:
            settle(desk, e, "pending", "another merge moved the meeting's frame", now_ns)
        elif now_ns * 1e-9 > m.until_s:
            settle(desk, e, "refuted", "the robots did not meet where the maps said",
                         now_ns)
        elif _both_there(m, other.meeting, now_ns):
            settle(desk, e, "refuted", f"both robots stood at the place the maps agree on "
                   f"for {MEET_SEEN_S:.0f} s and saw no tag of each other: not one place",
                   now_ns)


def _both_there(m: Meeting, other: Meeting | None, now_ns: int) -> bool:
    """Both robots of a meeting reached their places ``MEET_SEEN_S`` ago or more. Under a
    true transform they cannot both: the places are one, and the first there stands in the
    other's way, which then sees it (and its tag) on its way."""
    if other is None or not (m.arrived_ns and other.arrived_ns):
        return False
    return now_ns - max(m.arrived_ns, other.arrived_ns) > MEET_SEEN_S * 1e9


def _agrees(desk: MapMatchDesk, e: HypothesisEntry, rec: MergeRecord) -> bool:
    """The merge joined the hypothesis' two teams under (about) its transform."""
    if (rec.team_id, rec.joined_team_id) == (e.team_a, e.team_b):
        T = rec.T_joint
    elif (rec.team_id, rec.joined_team_id) == (e.team_b, e.team_a):
        T = inverse(rec.T_joint)
    else:
        return False
    at_b = transform_points(inverse(e.T_ab), np.zeros((1, 2)))[0]
    return same_transform(T, e.T_ab, at_b)


def settle(desk: MapMatchDesk, e: HypothesisEntry, status: str, why: str, now_ns: int) -> None:
    robots = [r.robot_id for r in end(desk, e)]
    e.status, e.reason = status, why
    if status == "refuted":
        desk.counters.meetings_refuted += 1
    log.info("meeting of %s: %s", robots, why)
    desk.events.emit("meeting", robots, e.team_a, f"meeting of {', '.join(robots)}: {why}",
                     now_ns)


def end(desk: MapMatchDesk, e: HypothesisEntry) -> list[RobotContext]:
    idx = desk.log.index(e)
    ended = [r for r in desk.fleet.robots.values()
             if r.meeting is not None and r.meeting.hypothesis == idx]
    for r in ended:
        stop(r)
    return ended


def stop(r: RobotContext) -> None:
    r.meeting = None
    r.nav.drop_target()      # decide afresh: the map and the team may have changed


def _length(path: F64) -> float:
    return float(np.hypot(*np.diff(path, axis=0).T).sum()) if len(path) > 1 else 0.0
