"""Merges found on the maps, and the meetings planned to settle what the maps leave open.

Every ``teams.map_match_period_s`` one pair of teams (the one waiting longest) has its maps
matched (``server.rendezvous.mapmatch``). Its best hypothesis — a transform on which submaps
from several places of both maps agree — goes one of three ways:

- **accepted** (``teams.map_match_min_support`` places, both maps among them, clearly more
  than any contradicting set): proposed to the merger as a merge of kind ``map``, which checks
  it on the maps like any other (agreement, keyframe matches, their turn) and commits it;
- **some support** (``teams.meet_min_support`` places): a meeting. One robot of each team
  drives to one place of the overlap, the place as each team's map has it. If the transform is
  right they arrive at the same spot, see each other, and the tags merge them (the merge is
  then of kind ``meeting``); if they have not merged within ``teams.meet_timeout_s`` the
  transform is refuted and never tried again. Its places must come from both maps, more
  than any rival has. Fewer places (``map_match_min_support``), or places from one map only
  (one team's submaps found in the other's map, none the other way), are mostly a wrong
  fit, but they earn a meeting still when the two maps joined under the transform would
  cover the coverage threshold: the teams would be done if merged, and have nothing better
  to do than find each other. Such a "finishing" meeting is planned whatever the distance,
  and has the time its paths take;
- otherwise it is logged and nothing happens.

Every hypothesis is kept in ``log`` with its support and what became of it, for the run's
report. A query runs in a process of its own when the server has one (``pool``: it takes a
second or more for large maps), else right here (lockstep: the run must not depend on its
timing).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose, inverse, transform_points
from server.config import ServerConfig
from server.fleet.events import EventLog
from server.fleet.model import Fleet
from server.rendezvous import meetings
from server.rendezvous.counters import RendezvousCounters
from server.rendezvous.evidence import MergeProposal
from server.rendezvous.liveview import Contradictions
from server.rendezvous.mapmatch import (
    Candidate,
    Hypothesis,
    MatchParams,
    PairResult,
    best_hypothesis,
    same_transform,
)
from server.rendezvous.maps import union_area_m2
from server.rendezvous.merger import Merger
from server.rendezvous.submaps import submap_candidates

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

#: transforms are checked against the robots' latest scans this often [s] (whatever the
#: number of robots: each check looks at every pair of robots of the two teams)
LOOK_PERIOD_S = 0.25
#: σ of a map-matched transform as the merger weighs it (the keyframe matches then refine it)
MAP_SIGMA_M, MAP_SIGMA_DEG = 0.3, 2.0


@dataclass
class HypothesisEntry:
    """One transform a pair of teams' maps suggested, and what became of it."""

    first_ns: int
    last_ns: int
    team_a: str
    team_b: str
    anchor_a: str             # the robots whose first poses are the teams' frames
    anchor_b: str
    T_ab: F64                 # team b's frame -> team a's
    support: int
    side_a: int
    side_b: int
    rival: int
    acceptance: float
    status: str = "pending"   # pending, meeting, accepted, refused, confirmed, refuted
    reason: str = ""
    seen: int = 1             # queries that found it
    #: the coverage of the two maps joined under T_ab, at its latest query while pending
    union_coverage: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"first_ns": self.first_ns, "last_ns": self.last_ns, "team_a": self.team_a,
                "team_b": self.team_b, "anchor_a": self.anchor_a, "anchor_b": self.anchor_b,
                "T_ab": [float(v) for v in self.T_ab], "support": self.support,
                "side_a": self.side_a, "side_b": self.side_b, "rival": self.rival,
                "acceptance": self.acceptance, "status": self.status, "reason": self.reason,
                "seen": self.seen, "union_coverage": self.union_coverage}


@dataclass
class _Job:
    team_a: str
    team_b: str
    members: tuple[tuple[str, ...], tuple[str, ...]]   # the teams as they were asked
    picked: list[tuple[str, int]]                      # the submaps asked for
    future: Future[PairResult] | None = None


@dataclass
class PairMemory:
    """What the queries of one pair of teams found, while neither team changes: submap
    centres (each team's frame), when each was last matched, and its candidates. Each query
    matches the submaps never matched yet (newest first), then those matched longest ago, so
    that over a few queries every part of both maps has been tried, at a bounded cost each."""

    members: tuple[tuple[str, ...], tuple[str, ...]]
    centres: dict[str, list[F64]] = field(default_factory=lambda: {"a": [], "b": []})
    matched_ns: dict[tuple[str, int], int] = field(default_factory=dict)
    cands: dict[tuple[str, int], list[Candidate]] = field(default_factory=dict)

    def register(self, side: str, positions: F64, spacing_m: float) -> None:
        have = self.centres[side]
        for xy in positions[::-1]:
            if all(math.hypot(*(xy - q)) >= spacing_m for q in have):
                have.append(np.asarray(xy, dtype=np.float64).copy())

    def pick(self, side: str, n: int) -> list[tuple[int, F64]]:
        ids = sorted(range(len(self.centres[side])),
                     key=lambda i: (self.matched_ns.get((side, i), -1), -i))
        return [(i, self.centres[side][i]) for i in ids[:n]]

    def candidates(self) -> list[Candidate]:
        return [c for cs in self.cands.values() for c in cs]


class MapMatchDesk:
    """Map-matched merges and planned meetings between teams (see the module docstring)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, merger: Merger, events: EventLog,
                 counters: RendezvousCounters) -> None:
        self.cfg, self.fleet, self.merger = cfg, fleet, merger
        self.events, self.counters = events, counters
        self.log: list[HypothesisEntry] = []
        self.asked_ns: dict[tuple[str, str], int] = {}
        self.next_ns = 0
        self.query_ms: list[float] = []          # the latest queries' times (one per submap)
        self.memory: dict[tuple[str, str], PairMemory] = {}
        self._job: _Job | None = None
        #: looks that found open floor where a transform puts a robot (``liveview``)
        self.looks = Contradictions()
        self.look_next_ns = 0
        #: where queries run (the server's matcher process; ``ServerCore.use_pools``),
        #: None: here
        self.matcher: Callable[[int], Executor | None] | None = None

    def __getstate__(self) -> dict[str, object]:
        # a query in flight is asked again; processes are not state
        return {**self.__dict__, "_job": None, "matcher": None}

    @property
    def params(self) -> MatchParams:
        t = self.cfg.teams
        return MatchParams(min_support=t.map_match_min_support)

    # -- the period's work -------------------------------------------------------------------
    def tick(self, now_ns: int) -> None:
        t = self.cfg.teams
        planner = None if self.matcher is None else self.matcher(len(self.fleet.teams))
        meetings.follow(self, now_ns)
        self._look(now_ns)
        if not t.enabled or not t.map_match:
            return
        job = self._job
        if job is not None and job.future is not None and job.future.done():
            self._job = None
            try:
                self._take(job, job.future.result(), now_ns)
            except Exception as e:      # a pool process died: ask again later
                log.warning("a map matching job failed: %s", e)
        if now_ns < self.next_ns or self._job is not None:
            return
        self.next_ns = now_ns + int(t.map_match_period_s * 1e9)
        pair = self._next_pair()
        if pair is None:
            return
        a, b = pair
        self.asked_ns[pair] = now_ns
        teams, p = self.fleet.teams, self.params
        members = (tuple(teams[a].robot_ids), tuple(teams[b].robot_ids))
        mem = self.memory.get(pair)
        if mem is None or mem.members != members:   # a merge or split: frames moved
            mem = self.memory[pair] = PairMemory(members)
        mem.register("a", self._keyframes_xy(a), p.spacing_m)
        mem.register("b", self._keyframes_xy(b), p.spacing_m)
        pick_a, pick_b = mem.pick("a", p.max_submaps), mem.pick("b", p.max_submaps)
        job = _Job(a, b, members, [("a", i) for i, _ in pick_a] + [("b", i) for i, _ in pick_b])
        args = (self.fleet.team_grid(a), self.fleet.team_grid(b), pick_a, pick_b, p)
        if planner is not None:
            try:
                job.future = planner.submit(submap_candidates, *args)
                self._job = job
                return
            except RuntimeError as e:   # the pool is shutting down or broken: match here
                log.warning("matching maps here: the planner pool is gone (%s)", e)
        self._take(job, submap_candidates(*args), now_ns)

    def _look(self, now_ns: int) -> None:
        """Transforms not settled yet, checked against what the robots see now
        (``liveview``): one whose robots look where it puts another and see open floor is
        refuted (its meeting, if any, ended)."""
        if now_ns < self.look_next_ns:
            return
        self.look_next_ns = now_ns + int(LOOK_PERIOD_S * 1e9)
        teams = self.fleet.teams
        for k, e in enumerate(self.log):
            if e.status not in ("pending", "meeting"):
                continue
            if e.team_a not in teams or e.team_b not in teams:
                continue        # a team merged or gone: its frame moved, asked again later
            why = self.looks.check(self.fleet, k, e.team_a, e.team_b, e.T_ab)
            if why is None:
                continue
            self.counters.map_refuted_by_view += 1
            self.looks.forget(k)
            if e.status == "meeting":
                meetings.settle(self, e, "refuted", why, now_ns)
            else:
                e.status, e.reason = "refuted", why
                log.info("maps of %s and %s: transform refuted: %s", e.team_b, e.team_a, why)

    def _next_pair(self) -> tuple[str, str] | None:
        """The pair of live teams with maps that waited longest; the larger team first (it
        absorbs the other, as its frame holds more robots)."""
        fleet = self.fleet
        live = [tm for tm in fleet.teams.values()
                if not tm.known and any(fleet.robots[r].alive for r in tm.robot_ids)
                and sum(len(fleet.robots[r].slam.keyframes) for r in tm.robot_ids) >= 5]
        live.sort(key=lambda tm: (-len(tm.robot_ids), tm.team_id))
        pairs = [(x.team_id, y.team_id) for i, x in enumerate(live) for y in live[i + 1:]]
        for gone in set(self.memory) - set(pairs):
            del self.memory[gone]
        if not pairs:
            return None
        return min(pairs, key=lambda p: self.asked_ns.get(p, -1))

    def _keyframes_xy(self, team_id: str) -> F64:
        fleet = self.fleet
        rows = [fleet.robots[r].slam.keyframe_poses()[:, :2]
                for r in fleet.teams[team_id].robot_ids if fleet.robots[r].slam.keyframes]
        return np.concatenate(rows) if rows else np.zeros((0, 2))

    # -- a query's answer --------------------------------------------------------------------
    def _take(self, job: _Job, res: PairResult, now_ns: int) -> None:
        fleet = self.fleet
        ta, tb = fleet.teams.get(job.team_a), fleet.teams.get(job.team_b)
        if ta is None or tb is None or (tuple(ta.robot_ids), tuple(tb.robot_ids)) != job.members:
            return   # a merge or split meanwhile: the frames moved
        self.counters.map_queries += 1
        self.query_ms = (self.query_ms + res.query_ms)[-2000:]
        mem = self.memory.get((job.team_a, job.team_b))
        if mem is None or mem.members != job.members:
            return
        for key in job.picked:
            mem.matched_ns[key] = now_ns
            mem.cands[key] = [c for c in res.candidates if (c.side, c.submap) == key]
        h = best_hypothesis(mem.candidates(), self.params)
        if h is None or h.support < min(self.cfg.teams.meet_min_support,
                                        self.params.min_support):
            return
        entry = self._entry(ta.team_id, tb.team_id, ta.anchor, tb.anchor, h, now_ns)
        if entry.status in ("refuted", "refused"):
            return
        self._decide(entry, h, now_ns)

    def _decide(self, entry: HypothesisEntry, h: Hypothesis, now_ns: int) -> None:
        """A merge, a meeting, or nothing yet (see the module docstring)."""
        one_sided = min(h.side_support("a"), h.side_support("b")) == 0
        finish = entry.status == "pending" and self._would_finish(entry)
        if h.accepted(self.params):
            self._merge(entry, now_ns)
        elif entry.status == "pending" and self.cfg.teams.map_match_meet and \
                h.support > h.rival_support and \
                ((h.support >= self.cfg.teams.meet_min_support and not one_sided) or finish):
            # more places than any rival, seen from both maps, but not clearly enough: meet.
            # Seen from one map only, or at fewer places, such a transform is mostly wrong,
            # and a meeting is planned on it only when the two maps joined by it would
            # finish the exploration: then the teams have nothing left but each other to
            # find (a wrong one costs the two robots' drive, which a look often cuts short)
            if finish:
                log.info("maps of %s and %s joined under T %s would cover %.1f %%: a "
                         "meeting%s", entry.team_b, entry.team_a, entry.T_ab.round(2),
                         100 * (entry.union_coverage or 0),
                         ", though only one map's places fit the other" if one_sided else "")
            meetings.arrange(self, entry, h, now_ns, finishing=finish)

    def _would_finish(self, e: HypothesisEntry) -> bool:
        """The two teams' latest maps joined under the entry's transform cover the coverage
        threshold (``explore``): merged now, the teams would be done. The coverage is kept
        in the entry (``union_coverage``)."""
        total = self.cfg.explore.total_area_m2
        ga, gb = self.fleet.latest_grids.get(e.team_a), self.fleet.latest_grids.get(e.team_b)
        if not total or ga is None or gb is None:
            return False
        e.union_coverage = round(union_area_m2(ga, gb, e.T_ab) / total, 4)
        return e.union_coverage >= self.cfg.explore.coverage_threshold

    def _entry(self, a: str, b: str, anchor_a: str, anchor_b: str, h: Hypothesis,
               now_ns: int) -> HypothesisEntry:
        """The pair's entry for this transform: an earlier one that agrees, or a new one."""
        at_b = np.mean([transform_points(inverse(c.T_ab), c.centre_a[None, :])[0]
                        for c in h.members], axis=0)
        for e in reversed(self.log):
            if (e.team_a, e.team_b) == (a, b) and same_transform(e.T_ab, h.T_ab, at_b):
                if e.status in ("pending", "meeting"):
                    e.T_ab, e.support, e.rival = h.T_ab, h.support, h.rival_support
                    e.side_a, e.side_b = h.side_support("a"), h.side_support("b")
                    e.acceptance = round(h.acceptance, 4)
                e.last_ns, e.seen = now_ns, e.seen + 1
                return e
        e = HypothesisEntry(now_ns, now_ns, a, b, anchor_a, anchor_b, h.T_ab, h.support,
                            h.side_support("a"), h.side_support("b"), h.rival_support,
                            round(h.acceptance, 4))
        self.log.append(e)
        self.counters.map_hypotheses += 1
        log.info("maps of %s and %s fit under T %s at %d places (rival %d)", b, a,
                 h.T_ab.round(2), h.support, h.rival_support)
        return e

    def _merge(self, e: HypothesisEntry, now_ns: int) -> None:
        t_ab = e.T_ab
        sig = np.array([MAP_SIGMA_M, MAP_SIGMA_M, math.radians(MAP_SIGMA_DEG)])
        ra, rb = self.fleet.robots[e.anchor_a], self.fleet.robots[e.anchor_b]
        T_own = compose(compose(inverse(ra.own_frame_in_team()), t_ab), rb.own_frame_in_team())
        T_team, link = self.merger.surgery.own_frames_link(e.anchor_a, e.anchor_b, T_own, sig,
                                                           "map", now_ns)
        meetings.end(self, e)
        rec = self.merger.try_merge(MergeProposal(e.team_a, e.team_b, (), T_team,
                                                  np.diag(sig ** 2), T_team), now_ns, (link,),
                                    kind="map")
        if rec is None:
            e.status, e.reason = "refused", "the merger's map checks"
            return
        e.status = "accepted"
        self.counters.map_merges += 1

    def hypotheses(self) -> list[dict[str, Any]]:
        return [e.as_dict() for e in self.log]

