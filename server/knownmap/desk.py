"""A mission on a known map: robots placed in it, lost robots found again, the map kept up.

The core hands every scan to ``KnownMapDesk.on_scan`` after SLAM has placed it in the robot's
own map. What happens depends on where the robot stands:

1. **Not placed** (its team is not the known map's): every ``known_map.query_period_s`` its
   team's map is matched against the known map (``placing``); a placement that wins
   ``known_map.confirmations`` queries in a row (``search``) goes to the merger, which checks
   it as any merge on the maps (the maps must not contradict each other, and the robot's own
   keyframes must match the map where they overlap) and joins the team's graph to the map's.
2. **Placed**: its scan is laid on the map (``watch``). Scans that disagree for
   ``known_map.lost_after_s`` make it lost: it leaves the map's team, its keyframes from
   before stay there (``ghosts.detach``), and it searches afresh from step 1.
3. **Placed, extend mode**: its new keyframes are compared with the map, and the map's views
   they show to be out of date are retired (``changes``).

Until placed, a robot is its own team and explores as one. No I/O here.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas import Scan
from schemas.messages import Localisation
from schemas.se2 import compose, inverse
from server.config import ServerConfig
from server.fleet.events import EventLog
from server.fleet.model import Fleet, RobotContext, Team
from server.knownmap import ghosts, tellapart
from server.knownmap.changes import SUPPORT, Upkeep
from server.knownmap.ghosts import MAP_ID, MAP_TEAM
from server.knownmap.mapdata import KnownMap
from server.knownmap.placing import MapTarget, candidates, clear_winner, placements
from server.knownmap.search import Guess, Search
from server.knownmap.views import consolidated
from server.knownmap.watch import LossWatch, scan_agreement, scan_points
from server.rendezvous.evidence import MergeProposal
from server.rendezvous.mapmatch import Layers, MatchParams, layers
from server.rendezvous.merger import MergeDeferred, Merger, MergeRefused
from server.slam.grid import OccupancyGrid
from server.slam.mapping import render_grid

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: σ of a placement as the merger weighs it (the keyframe matches then refine it)
PLACE_SIGMA_M, PLACE_SIGMA_DEG = 0.3, 2.0


@dataclass
class MapVersion:
    """The known map's own grid as queries and the loss watch read it, made again when the
    map changes (not kept in a snapshot: made again on demand)."""

    version: int
    target: MapTarget | None = None
    layers: Layers | None = None
    older: Layers | None = None     # extend: the older keyframes' alone (``changes``)
    clear: NDArray[np.bool_] | None = None   # its open floor away from walls (``tellapart``)


class KnownMapDesk:
    """Placing robots in a known map and keeping them there (see the module docstring)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, merger: Merger, events: EventLog,
                 known: KnownMap) -> None:
        self.cfg, self.fleet, self.merger, self.events = cfg, fleet, merger, events
        self.k = cfg.known_map
        self.extend = self.k.mode == "extend"
        self.known_anchor, self.missions = known.anchor, known.missions
        self.notes = dict(known.notes)
        ghosts.add_map(fleet, known)
        #: each keyframe's source, for the graphs that hold a known map's
        self.sources: dict[str, list[str]] = {MAP_ID: list(known.sources)}
        self.searches: dict[str, Search] = {}
        self.watches: dict[str, LossWatch] = {}
        self.lost: dict[str, int] = {}          # robots lost and not placed again: since
        self.placed_at: dict[str, int] = {}     # when each robot was last placed
        self.tell_next: dict[str, int] = {}     # when a searching robot is next sent on
        self.counts = {"queries": 0, "placed": 0, "refused": 0, "lost": 0, "by_hand": 0,
                       "tell_apart": 0}
        self.version = 0                        # of the map's own keyframes
        self._view: MapVersion | None = None
        #: extend: the map kept up to date by what placed robots see (``changes``)
        self.upkeep = Upkeep(self.k) if self.extend else None
        if not self.extend:
            # nothing to explore: the map stays as it is, the robots wait for orders
            team = fleet.teams[MAP_TEAM]
            team.finished, team.finished_stamp_ns = True, 0

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_view": None}   # made again from the map on demand

    @property
    def params(self) -> MatchParams:
        w = self.k.window_m
        return MatchParams(submap_m=w, spacing_m=w / 2, max_submaps=3, top_k=4)

    # -- the map's own grid ------------------------------------------------------------------
    def view(self) -> MapVersion:
        v = self._view
        if v is None or v.version != self.version:
            grid = self._map_grid(self.extend)
            v = self._view = MapVersion(self.version, MapTarget(grid, self.params),
                                        layers(grid, self.params.cell_m))
            if self.extend:     # what this mission's keyframes are compared with
                v.older = layers(self._map_grid(False), self.params.cell_m)
        return v

    def _map_grid(self, added: bool) -> OccupancyGrid:
        """The map's grid: the keyframes its ghosts hold, not retired, and (``added``) those
        placed robots added to it so far."""
        fleet = self.fleet
        kfs: list[Any] = []
        poses = [np.zeros((0, 3))]
        for rid in fleet.teams[MAP_TEAM].robot_ids:
            r = fleet.robots[rid]
            if r.ghost or added:
                k, p = r.mapped_keyframes()
                kfs += list(k)
                poses.append(np.asarray(p).reshape(-1, 3))
        return render_grid(fleet.stages.mapper().params, kfs, np.concatenate(poses))

    def map_changed(self) -> None:
        """The map's own keyframes changed (retired, trimmed): its grid is made again."""
        self.version += 1
        team = self.fleet.teams[MAP_TEAM]
        team.mapper = self.fleet.stages.mapper()

    # -- per scan ----------------------------------------------------------------------------
    def on_scan(self, r: RobotContext, scan: Scan, ranges: F64, angles: F64,
                now_ns: int) -> None:
        """A scan SLAM has just placed in ``r``'s map (``ranges`` without teammates)."""
        if r.team_id == MAP_TEAM:
            self._watch(r, scan, ranges, angles)
            return
        team = self.fleet.team_of(r)
        s = self.searches.get(team.team_id)
        members = tuple(team.robot_ids)
        if s is None or s.members != members:
            s = self.searches[team.team_id] = Search(members, next_ns=now_ns)
        if now_ns >= s.next_ns and r.slam.keyframes:
            s.next_ns = now_ns + int(self.k.query_period_s * 1e9)
            self._query(team, s, now_ns)

    def _query(self, team: Team, s: Search, now_ns: int) -> None:
        fleet, p = self.fleet, self.params
        xy = np.concatenate([fleet.robots[rid].slam.keyframe_poses()[:, :2]
                             for rid in team.robot_ids if fleet.robots[rid].slam.keyframes])
        own = fleet.team_grid(team.team_id)
        target = self.view().target
        assert target is not None
        ranked = placements(candidates(target, own, xy, p), p)
        self.counts["queries"] += 1
        anchor = fleet.robots[team.anchor]
        winner = clear_winner(ranked, self.k.clear_ratio)
        if winner is None and len(ranked) > 1:     # alike: has it seen what tells them apart?
            mine = layers(own, tellapart.CELL_M)
            winner = tellapart.told_apart(ranked, self.k.clear_ratio, mine,
                                          tellapart.clear_layer(mine), *self.open_floor())
        guess = s.take(ranked, winner, anchor.pose, now_ns)
        if guess is not None and guess.may_retry(len(xy)) and \
                guess.wins >= self.k.confirmations:
            self.place(team, guess, now_ns)

    def place(self, team: Team, guess: Guess, now_ns: int, kind: str = "placed") -> bool:
        """Put a guess to the merger's checks; join the team to the map's if they pass."""
        fleet = self.fleet
        sig = np.array([PLACE_SIGMA_M, PLACE_SIGMA_M, math.radians(PLACE_SIGMA_DEG)])
        ra, rb = fleet.robots[fleet.teams[MAP_TEAM].anchor], fleet.robots[team.anchor]
        T_own = compose(compose(inverse(ra.own_frame_in_team()), guess.T_map_own),
                        rb.own_frame_in_team())
        surgery = self.merger.surgery
        T_team, link = surgery.own_frames_link(ra.robot_id, rb.robot_id, T_own, sig, kind,
                                               now_ns)
        proposal = MergeProposal(MAP_TEAM, team.team_id, (), T_team, np.diag(sig ** 2), T_team)
        info: dict[str, Any] = {}
        try:
            self.merger.verify(proposal, "placed", info)
        except MergeDeferred:
            return False                # too little of the robot's map yet: ask again
        except MergeRefused as e:
            guess.refused(str(e), sum(len(fleet.robots[rid].slam.keyframes)
                                      for rid in team.robot_ids))
            self.counts["refused"] += 1
            self.events.emit("merge_rejected", list(team.robot_ids), MAP_TEAM,
                             f"{team.team_id} not placed in the known map: {e}", now_ns)
            return False
        robots = list(team.robot_ids)
        self.merger.commit(proposal, now_ns, info, (link,), kind=kind)
        guess.status = "placed"
        self.searches.pop(team.team_id, None)
        for rid in robots:
            r = fleet.robots[rid]
            r.unmapped = not self.extend
            self.lost.pop(rid, None)
            self.placed_at[rid] = now_ns
            self.watches[rid] = LossWatch(self.k.lost_conflict_ratio, self.k.lost_after_s,
                                          good_keyframes=len(r.slam.keyframes))
            x, y, th = (float(v) for v in r.pose)
            self.events.emit("robot_joined", [rid], MAP_TEAM,
                             f"robot {rid} placed in the known map at ({x:.2f}, {y:.2f}, "
                             f"{math.degrees(th):.0f}°){' by hand' if kind != 'placed' else ''}",
                             now_ns, transform=(x, y, th))
        self.counts["placed"] += 1
        return True

    # -- placed robots -----------------------------------------------------------------------
    def _watch(self, r: RobotContext, scan: Scan, ranges: F64, angles: F64) -> None:
        stamp_ns = scan.stamp_ns
        w = self.watches.get(r.robot_id)
        if w is None:       # placed another way (tags with a placed robot): watched from now
            w = self.watches[r.robot_id] = LossWatch(self.k.lost_conflict_ratio,
                                                     self.k.lost_after_s)
            self.placed_at.setdefault(r.robot_id, stamp_ns)
            r.unmapped = not self.extend      # localize: what it sees is not added either
        lay = self.view().layers
        assert lay is not None
        a = scan_agreement(lay, r.pose, scan_points(ranges, angles, r.sensor_range_m))
        if not w.update(a, stamp_ns, len(r.slam.keyframes)):
            if self.upkeep is not None and w.bad_since_ns is None:
                older = self.view().older
                assert older is not None
                self._keep_up(r, older, stamp_ns)
        else:
            self._lose(r, w, stamp_ns)
            # it starts afresh from this scan, its first keyframe
            r.slam.add_scan(stamp_ns, scan.odom_pose, ranges, angles, r.sensor_range_m)
            r.pose = r.slam.pose
            r.start_pose = r.pose.copy()

    def _keep_up(self, r: RobotContext, lay: Layers, stamp_ns: int) -> None:
        """Extend: ``r``'s new keyframes compared with the map; what they show out of date
        retired or cut (``changes``), now and then, and the changed regions reported."""
        assert self.upkeep is not None
        self.upkeep.on_scan(self.fleet, MAP_TEAM, r, lay)
        done = self.upkeep.apply(self.fleet, stamp_ns)
        if done is None:
            return
        counts, regions = done
        if any(counts.values()):
            self.map_changed()
        for xy in regions:
            if len(xy) <= SUPPORT:      # a few more cells of a change reported before
                continue
            (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
            self.events.emit(
                "map_changed", [r.robot_id], MAP_TEAM,
                f"the building has changed at ({x0:.1f}, {y0:.1f})–({x1:.1f}, {y1:.1f}): "
                f"{len(xy)} cells; the map's views that showed it otherwise cut",
                stamp_ns, figures={"x0": float(x0), "y0": float(y0), "x1": float(x1),
                                   "y1": float(y1), "cells": float(len(xy)),
                                   **{k: float(v) for k, v in counts.items()}})

    def inspect_goal(self, r: RobotContext) -> tuple[float, float] | None:
        """Where ``r`` (without an errand) is sent: searching, where its placements differ
        (``tellapart``); placed, extend with ``known_map.inspect``, its next place on the
        pass over the map (``changes.Upkeep.inspect_goal``). None: nowhere."""
        if r.team_id != MAP_TEAM:
            return self._tell_apart(r)
        if self.upkeep is None or not self.k.inspect or r.robot_id not in self.watches:
            return None
        return self.upkeep.inspect_goal(self.fleet, MAP_TEAM, r)

    def _tell_apart(self, r: RobotContext) -> tuple[float, float] | None:
        """A searching robot whose latest query left several placements about as strong:
        where it sees what tells them apart (``tellapart.errand_goal``), asked at most once
        a query period."""
        team = self.fleet.team_of(r)
        s = self.searches.get(team.team_id)
        now = r.last_stamp_ns
        if s is None or len(s.shown) < 2 or now < self.tell_next.get(r.robot_id, 0):
            return None
        self.tell_next[r.robot_id] = now + int(self.k.query_period_s * 1e9)
        best = s.shown[0][1]
        Ts = [T for T, strength, _ in s.shown if strength >= tellapart.SHARE * best > 0]
        own = layers(self.fleet.team_grid(team.team_id), tellapart.CELL_M)
        goal = tellapart.errand_goal(*self.open_floor(), own,
                                     tellapart.clear_layer(own), Ts, r.pose)
        if goal is not None:
            self.counts["tell_apart"] = self.counts.get("tell_apart", 0) + 1
            log.info("%s sent to (%.1f, %.1f) to tell %d placements apart", r.robot_id,
                     *goal, len(Ts))
        return goal

    def on_pass(self, team: Team) -> bool:
        """The map's team is on its pass over the map (extend, ``inspect``): not done yet,
        whatever its coverage (the map it started with has it)."""
        return (team.team_id == MAP_TEAM and self.upkeep is not None and self.k.inspect
                and not self.upkeep.inspected)

    def open_floor(self) -> tuple[Layers, NDArray[np.bool_]]:
        """The map's layers and its open floor away from walls (``tellapart``)."""
        v = self.view()
        assert v.layers is not None
        if v.clear is None:
            v.clear = tellapart.clear_layer(v.layers)
        return v.layers, v.clear

    def inspect_stale(self, r: RobotContext) -> bool:
        """``r``'s place on the pass has little left to see again: it is sent on."""
        return r.team_id == MAP_TEAM and self.upkeep is not None and \
            self.upkeep.inspect_stale(self.fleet, r)

    def unreachable(self, goal: tuple[float, float], why: str) -> None:
        log.info("goal (%.1f, %.1f) skipped: %s", *goal, why)

    def _lose(self, r: RobotContext, w: LossWatch, stamp_ns: int) -> None:
        why = (f"{w.last.conflict} of {w.last.known} returns on mapped ground in open space "
               f"for {(stamp_ns - (w.bad_since_ns or stamp_ns)) * 1e-9:.1f} s")
        if self.upkeep is not None and self.upkeep.forget(self.fleet, r.robot_id,
                                                          w.good_keyframes):
            self.map_changed()
        ghosts.detach(self.fleet, r, w.good_keyframes, stamp_ns)
        del self.watches[r.robot_id]
        self.lost[r.robot_id] = stamp_ns
        self.counts["lost"] += 1
        log.warning("robot %s lost: %s", r.robot_id, why)
        self.events.emit("robot_lost", [r.robot_id], r.team_id,
                         f"robot {r.robot_id} lost in the known map ({why}): placed again "
                         "once found", stamp_ns)

    # -- what others read --------------------------------------------------------------------
    def state_of(self, r: RobotContext) -> Localisation:
        """searching, placed or lost (searching again after it was lost)."""
        if r.team_id == MAP_TEAM:
            return "placed"
        return "lost" if r.robot_id in self.lost else "searching"

    def states(self) -> list[dict[str, Any]]:
        """Each robot's localisation state and, while it searches, its best placements."""
        out = []
        for r in self.fleet.robots.values():
            if r.ghost:
                continue
            s = self.searches.get(r.team_id)
            out.append({"robot_id": r.robot_id, "state": self.state_of(r),
                        "hypotheses": [] if s is None or r.team_id == MAP_TEAM
                        else s.hypotheses(r.pose),
                        "queries": 0 if s is None else s.queries})
        return out

    def mission_map(self) -> KnownMap | None:
        """The map this mission leaves: the known map with what it added (extend) and without
        what it retired, for the next mission."""
        known = ghosts.team_map(self.fleet, MAP_TEAM, self.missions + 1, self.sources,
                                self.notes)
        if known is not None:
            known.anchor = self.known_anchor
        if known is not None and self.extend:
            known, dropped = consolidated(known, self.k.supersede_m)
            if dropped:
                log.info("map left: %d keyframes that newer ones see again dropped", dropped)
        return known

    def summary(self) -> dict[str, Any]:
        return {"mode": self.k.mode, "missions": self.missions, **self.counts,
                **({} if self.upkeep is None else {"upkeep": dict(self.upkeep.counts)}),
                "robots": {d["robot_id"]: d["state"] for d in self.states()},
                "placed_at_s": {rid: round(ns * 1e-9, 2) for rid, ns in self.placed_at.items()},
                "guesses": {tid: [g.as_dict() for g in s.guesses]
                            for tid, s in self.searches.items()}}
