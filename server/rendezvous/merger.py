"""Merging two teams' maps, and undoing a merge the evidence turns against.

A proposal (sightings the verifier found consistent, a known start pose, a marker) goes
through ``verify`` — the maps must not contradict each other under its transform, must match
where they overlap, and must not turn it beyond its uncertainty — and then ``commit`` joins
the two teams' graphs into one, refines it on the maps and lets the team explore together.
``verify`` raises ``MergeRefused`` (the evidence goes) or ``MergeDeferred`` (it stays, to be
proposed again). ``undo`` splits a team back along the merge that joined two robots whose
sightings contradict it. No I/O here.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose, inverse, transform_points
from server.config import ServerConfig
from server.fleet.events import EventLog
from server.fleet.model import Fleet, Link, MergeRecord, RobotContext, Team
from server.fleet.stages import Stages
from server.rendezvous.counters import RendezvousCounters
from server.rendezvous.evidence import MergeProposal, MergeVerifier, SightingRecord
from server.rendezvous.maps import (
    cross_matches,
    known_share,
    map_agreement,
    square_turn,
    square_walls_agree,
)
from server.rendezvous.surgery import KNOWN_MAP_RADIUS_M, GraphSurgery

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


#: the share of a keyframe's points that must find a partner in the other team's map for the
#: keyframe to confirm a map-matched merge (0.5 for merges on tag sightings)
MAP_KIND_MIN_INLIERS = 0.3
#: far sightings beside a narrow sensor (``teams.narrow_far_sightings``): the two maps' walls
#: must keep to a square grid this closely (``server.rendezvous.maps.wall_grid``), and the
#: sightings' transform turn b's grid onto a's within this [deg]
FAR_WALLS_ALIGNMENT = 0.5
FAR_WALLS_AGREE_DEG = 1.5
#: a pair of teams' sightings from one place are tried with the square walls' turn at most
#: this often [ns] (``Merger._one_place``)
ONE_PLACE_PERIOD_NS = 1_000_000_000


class MergeRefused(Exception):
    """The maps say no: the proposal's evidence is dropped."""


class MergeDeferred(Exception):
    """Not yet: the evidence stays until a map match confirms it."""


class Merger:
    """Verifies, commits and undoes merges of the fleet's teams (one thread)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, stages: Stages, surgery: GraphSurgery,
                 events: EventLog, counters: RendezvousCounters) -> None:
        self.cfg, self.fleet, self.stages, self.surgery = cfg, fleet, stages, surgery
        self.events, self.counters = events, counters
        self.verifier: MergeVerifier = stages.verifier()
        self._one_place_at: dict[tuple[str, str], int] = {}

    # -- proposals -------------------------------------------------------------------------
    def consider(self, team_a: str, team_b: str, rec: SightingRecord) -> None:
        """A sighting between two teams: merge when the verifier proposes it."""
        proposal = self.verifier.add(team_a, team_b, rec)
        if proposal is None:
            proposal = self._one_place(team_a, team_b, rec.stamp_ns)
        if proposal is not None:
            self.try_merge(proposal, rec.stamp_ns)

    def _one_place(self, team_a: str, team_b: str, stamp_ns: int) -> MergeProposal | None:
        """Beside a narrow sensor (``teams.narrow_far_sightings``): sightings of a robot that
        stands in one place (a camera robot stops for its sweeps) agree on where it is but
        cannot turn one frame onto the other, and the tags' yaws give the turn only to
        degrees. The square walls of both maps give it to a fraction of one, modulo a
        quarter turn, and the tags pick the quarter. Without this, the merge waited until
        the robot had moved, 30 s in one run, while the LIDAR robot mapped its room itself.
        At most once a second per pair of teams; the proposal is verified as any other."""
        t = self.cfg.teams
        ta, tb = self.fleet.teams[team_a], self.fleet.teams[team_b]
        robots = self.fleet.robots
        ids = (*ta.robot_ids, *tb.robot_ids)
        key = (min(team_a, team_b), max(team_a, team_b))
        if not t.narrow_far_sightings or not any(robots[r].slam.narrow for r in ids) or \
                stamp_ns - self._one_place_at.get(key, -1 << 62) < ONE_PLACE_PERIOD_NS:
            return None
        self._one_place_at[key] = stamp_ns
        place = self.verifier.one_place(team_a, team_b)
        short = place is None
        if short:
            # or a robot that has moved a little since it was first seen (it stood for a
            # whole scan, turned to find its caller, then drove): its places give the turn
            # to a few degrees, the walls to a fraction of one. Without this the merge
            # waited 2-3 s more for it to drive half a metre further, in two runs of eight
            place = self.verifier.short_path(team_a, team_b)
        if place is None:
            return None
        teams = self.fleet.teams
        turn = square_turn([robots[r].slam for r in teams[place.team_a].robot_ids],
                           [robots[r].slam for r in teams[place.team_b].robot_ids],
                           place.rough_turn_rad, 3.0 * place.rough_sigma_rad,
                           FAR_WALLS_ALIGNMENT)
        if turn is None:
            return None
        if short:
            self.counters.short_path_proposals += 1
        else:
            self.counters.one_place_proposals += 1
        return place.proposal(turn, math.radians(FAR_WALLS_AGREE_DEG))

    def try_merge(self, p: MergeProposal, stamp: int, extra_links: tuple[Link, ...] = (),
                  kind: str = "tags") -> MergeRecord | None:
        """Verify and commit a merge; ``extra_links`` join the graphs besides the proposal's
        sightings (a marker measured by hand between two recorded sessions)."""
        info: dict[str, Any] = {}
        try:
            self.verify(p, kind, info)
        except MergeDeferred:
            self.counters.merges_deferred += 1
            return None
        except MergeRefused as e:
            self._refuse(p, str(e), stamp)
            return None
        return self.commit(p, stamp, info, extra_links, kind)

    def verify(self, p: MergeProposal, kind: str, info: dict[str, Any]) -> None:
        """Check a proposal on the two teams' maps; ``info`` gets what was found."""
        t = self.cfg.teams
        ta, tb = self.fleet.teams[p.team_a], self.fleet.teams[p.team_b]
        grid_a = self.fleet.team_grid(ta.team_id)
        agree = map_agreement(grid_a, self.fleet.team_grid(tb.team_id), p.T_ab)
        info.update({"overlap_cells": agree.overlap_cells, "wall_cells": agree.occupied_checked,
                     "conflicts": agree.conflicts,
                     "conflict_ratio": round(agree.conflict_ratio, 4)})
        if agree.occupied_checked >= t.min_checked_cells and \
                agree.conflict_ratio > t.max_conflict_ratio:
            raise MergeRefused(f"maps disagree ({agree.conflicts} of {agree.occupied_checked} "
                               "wall cells)")
        tried = [0]
        robots = self.fleet.robots
        # a map-matched transform comes from places where the maps overlap, and it is at their
        # edge that the teams' keyframes are matched: a keyframe's scan also sees what the
        # other team has not mapped, so fewer of its points have a partner there
        on_maps = kind in ("map", "placed")   # placed: a robot in a known map (server.knownmap)
        inliers = MAP_KIND_MIN_INLIERS if on_maps else 0.5
        # a short, narrow sensor's keyframe near the other team's often sees the far face of
        # a wall it saw, or a room it never looked into: such a keyframe cannot pass, however
        # well the maps fit, and is no test of the fit (tried only where it could pass)
        seen = inliers if any(robots[r].slam.narrow
                              for r in (*ta.robot_ids, *tb.robot_ids)) else 0.0
        # a keyframe beside the other team's but in a room that team never looked into (an
        # office's rooms, a wall apart) is no test of the sightings' transform either: it
        # could not pass were the transform right (maps that fit alone keep the old test)
        known = None if on_maps else known_share(grid_a)
        matches = [m for ra in ta.robot_ids for rb in tb.robot_ids
                   for m in cross_matches(robots[ra].slam, robots[rb].slam, T_ab=p.T_ab,
                                          tried=tried, min_inlier_fraction=inliers,
                                          radius_m=KNOWN_MAP_RADIUS_M if kind == "placed"
                                          else 5.0, min_seen_fraction=seen, known=known)]
        found = len(matches)
        info["map_match_tries"], info["map_matches_before"] = tried[0], found
        if tried[0] >= t.min_map_match_tries and found == 0:
            raise MergeRefused(f"no part of the maps matches within 0.5 m ({tried[0]} tried)")
        if on_maps and found < 2:
            if kind == "placed" and tried[0] - found < 2:
                # too few of the robot's keyframes yet to say (one that does not match is
                # not yet a contradiction: it may see past the map's edge)
                raise MergeDeferred()
            # on the maps alone, the robots' own keyframes must confirm the fit too
            raise MergeRefused(f"{found} keyframe matches where the maps overlap "
                               f"({tried[0]} tried): too few for a merge on the maps alone")
        if matches:
            # where the maps do match, they say how the transform turns: far better than the
            # sightings (a small error across the line of sight turns it by degrees)
            turn = float(np.median([m.turn_rad for m in matches]))
            info["map_turn_deg"] = round(math.degrees(turn), 3)
            bound = t.max_map_turn_sigmas * math.sqrt(p.cov_ab[2, 2]) + math.radians(1.0)
            if abs(turn) > bound:
                raise MergeRefused(f"the maps turn the transform by {math.degrees(turn):.2f}° "
                                   f"({found} matches), beyond its uncertainty "
                                   f"({math.degrees(bound):.2f}°)")
        far = max((r.sighting.range_m for r in p.records), default=0.0)
        if far > t.max_sighting_range_m and found == 0 and kind == "tags" and not (
                seen and t.narrow_far_sightings and square_walls_agree(
                    [robots[r].slam for r in ta.robot_ids],
                    [robots[r].slam for r in tb.robot_ids], float(p.T_ab[2]),
                    FAR_WALLS_AGREE_DEG, FAR_WALLS_ALIGNMENT)):
            # sightings from afar (located by the LIDAR): a small error across the line of
            # sight turns the maps by a degree; wait until a map match confirms them. Not
            # beside a narrow sensor: its short views overlap the other map too little for a
            # match to come before the wide robot has mapped its room itself, so there the
            # sightings' turn is checked on the two maps' square walls instead
            raise MergeDeferred()

    def commit(self, p: MergeProposal, stamp: int, info: dict[str, Any],
               extra_links: tuple[Link, ...] = (), kind: str = "tags") -> MergeRecord:
        """Join team b into team a: one graph, refined on the maps, one team."""
        fleet = self.fleet
        ta, tb = fleet.teams[p.team_a], fleet.teams[p.team_b]
        b_anchor = fleet.robots[tb.anchor]
        b_origin_before = b_anchor.slam.keyframe_pose(0)
        links = [self.surgery.sighting_link(r) for r in p.records] + list(extra_links)
        self.surgery.rebuild(ta, [(rid, np.zeros(3)) for rid in ta.robot_ids]
                             + [(rid, p.T_ab) for rid in tb.robot_ids],
                             ta.links + tb.links + links)
        info["map_matches"] = self.surgery.refine_on_maps(ta.robot_ids, tb.robot_ids, links)
        info["sightings_retired"] = self.surgery.retire_sightings(ta.links + tb.links + links)
        T_joint = compose(b_anchor.slam.keyframe_pose(0), inverse(b_origin_before))
        for rid in tb.robot_ids:
            r = fleet.robots[rid]
            r.team_id = ta.team_id
            r.start_pose = compose(p.T_ab, r.start_pose)
            r.pose = r.slam.pose
        for xy in tb.visited.points_xy:
            ta.visited.add(transform_points(p.T_ab, np.asarray(xy).reshape(1, 2))[0])
        merged_ids = list(tb.robot_ids)
        ta.robot_ids = ta.robot_ids + merged_ids
        ta.links = [ln for ln in ta.links + tb.links + links if not ln.retired]
        tb.merged_into = ta.team_id
        tb.mapper = None          # its map is the joint team's now: no grid kept for it
        fleet.retired_teams[tb.team_id] = fleet.teams.pop(tb.team_id)
        fleet.latest_grids.pop(tb.team_id, None)
        self.verifier.forget(tb.team_id)
        fleet.coordinate(ta)
        rec = MergeRecord(stamp, ta.team_id, tb.team_id, [r for r in ta.robot_ids
                                                          if r not in merged_ids], merged_ids,
                          [(r.observer, r.observed, r.stamp_ns) for r in p.records],
                          p.T_ab, p.cov_ab, p.direct_first, T_joint, info, kind=kind)
        fleet.merges.append(rec)
        self.counters.merges += 1
        how = f"{len(p.records)} sightings" if kind == "tags" else f"a {kind} link"
        log.info("merged %s into %s from %s: T %s (before %s)", tb.team_id, ta.team_id, how,
                 T_joint.round(3), p.T_ab.round(3))
        self.events.emit("merge", ta.robot_ids, ta.team_id,
                         f"{tb.team_id} merged into {ta.team_id} from {how}", stamp,
                         transform=(float(T_joint[0]), float(T_joint[1]), float(T_joint[2])),
                         covariance=[float(v) for v in p.cov_ab.reshape(-1)])
        return rec

    def _refuse(self, p: MergeProposal, why: str, stamp: int) -> None:
        ta, tb = self.fleet.teams[p.team_a], self.fleet.teams[p.team_b]
        self.verifier.reject(p)
        self.fleet.refused(ta.team_id, tb.team_id, stamp)
        self.counters.merges_rejected += 1
        log.info("%s not merged into %s: %s (T %s from %d sightings)", tb.team_id, ta.team_id,
                 why, np.asarray(p.T_ab).round(3), len(p.records))
        self.events.emit("merge_rejected", ta.robot_ids + tb.robot_ids, ta.team_id,
                         f"{tb.team_id} not merged into {ta.team_id}: {why}", stamp)

    # -- links other than sightings --------------------------------------------------------
    def join_known_start(self, r: RobotContext, stamp_ns: int) -> None:
        """A robot placed at a known pose joins the team of the robots already placed so, as
        soon as it has a keyframe (the merge is still checked on the maps)."""
        t = self.cfg.teams
        starts = t.start_poses
        if not r.slam.keyframes:
            return  # its first scan was refused: try again with the next
        r.start_checked = True
        other = next((o for o in self.fleet.robots.values() if o is not r
                      and o.robot_id in starts and o.slam.keyframes
                      and o.team_id != r.team_id), None)
        if other is None:
            return  # the first one placed: the others join it
        S_a = np.asarray(starts[other.robot_id], dtype=np.float64)
        S_b = np.asarray(starts[r.robot_id], dtype=np.float64)
        sig = np.array([t.start_pose_sigma_m, t.start_pose_sigma_m,
                        math.radians(t.start_pose_sigma_deg)])
        T_team, link = self.surgery.own_frames_link(other.robot_id, r.robot_id,
                                                    compose(inverse(S_a), S_b), sig, "start",
                                                    stamp_ns)
        self.try_merge(MergeProposal(other.team_id, r.team_id, (), T_team, np.diag(sig ** 2),
                                     T_team), stamp_ns, (link,), kind="start")

    def add_team_sighting(self, team: Team, rec: SightingRecord) -> None:
        """A sighting between teammates that agrees with the team's graph: another factor,
        unless the maps already tie the pair or the last one is recent."""
        pair = {rec.observer, rec.observed}
        last = max((ln.stamp_ns for ln in team.links if {ln.a, ln.b} == pair), default=None)
        if self.surgery.tied_by_maps(team.links, rec.observer, rec.observed):
            return   # the maps say more about this pair than another sighting would
        if last is None or rec.stamp_ns - last >= self.cfg.teams.refine_period_s * 1e9:
            self.surgery.add_link(team, self.surgery.sighting_link(rec))
            self.counters.refined += 1

    # -- undo ------------------------------------------------------------------------------
    def undo(self, team: Team, stamp_ns: int, pair: tuple[str, str]) -> bool:
        """Split ``team`` back along the latest merge that put ``pair`` together, unless the
        maps of the two sides still match. Returns whether it was split."""
        merges = self.fleet.merges
        merge = next((m for m in reversed(merges) if m.team_id == team.team_id
                      and m.undone_stamp_ns is None
                      and (pair[0] in m.robots_b) != (pair[1] in m.robots_b)), None)
        if merge is None or any(m.team_id == team.team_id and m.stamp_ns > merge.stamp_ns
                                and m.undone_stamp_ns is None for m in merges):
            log.warning("sightings contradict team %s but its latest merge does not separate "
                        "%s and %s: kept", team.team_id, *pair)
            return False
        side_b = [r for r in team.robot_ids if r in merge.robots_b]
        side_a = [r for r in team.robot_ids if r not in merge.robots_b]
        if self.cfg.teams.refine_on_maps and self.surgery.maps_still_match(side_a, side_b):
            # the maps fit where they overlap: more likely a tag misread as a teammate's
            self.counters.contradictions_overruled += 1
            log.warning("sightings contradict %s and %s in %s, but their maps still match: "
                        "merge kept", *pair, team.team_id)
            return False
        old = self._split(team, merge.joined_team_id, side_a, side_b)
        merge.undone_stamp_ns = stamp_ns
        self.counters.merges_undone += 1
        log.warning("%s split from %s: sightings between %s and %s contradict the merge",
                    old.team_id, team.team_id, *pair)
        self.events.emit("merge_undone", side_a + side_b, team.team_id,
                         f"{old.team_id} split from {team.team_id}: sightings contradict the "
                         "merge", stamp_ns)
        return True

    def _split(self, team: Team, old_id: str, side_a: list[str], side_b: list[str]) -> Team:
        """Team ``old_id`` back out of ``team`` with the robots of ``side_b``, each side in
        its own graph again, both exploring."""
        fleet = self.fleet
        old = fleet.retired_teams.pop(old_id)
        b_anchor = fleet.robots[old.anchor]
        T_team_b = compose(b_anchor.slam.keyframe_pose(0),
                           inverse(b_anchor.slam.trajectory.prior_pose()))
        inside_a = [ln for ln in team.links if ln.a in side_a and ln.b in side_a]
        inside_b = [ln for ln in team.links if ln.a in side_b and ln.b in side_b]
        for ln in team.links:
            if ln not in inside_a and ln not in inside_b:
                ln.record.index = None
        back = inverse(T_team_b)
        old.robot_ids, old.links, old.merged_into = side_b, inside_b, None
        old.mapper = self.stages.mapper()
        team.robot_ids, team.links = side_a, inside_a
        for t_ in (team, old):  # each part judges its own coverage again
            t_.finished, t_.finished_stamp_ns = False, None
        for rid in side_a + side_b:
            fleet.robots[rid].nav.resume()
        team.mapper = self.stages.mapper()
        fleet.teams[old.team_id] = old
        self.surgery.rebuild(team, [(rid, np.zeros(3)) for rid in side_a], inside_a)
        self.surgery.rebuild(old, [(rid, back) for rid in side_b], inside_b)
        for rid in side_b:
            r = fleet.robots[rid]
            r.team_id = old.team_id
            r.start_pose = compose(back, r.start_pose)
        fleet.coordinate(team)
        fleet.coordinate(old)
        return old
