"""Keeping a known map up to date in ``extend`` mode: newer views retire the older ones.

The map is drawn from keyframes; an out-of-date map is older keyframes that no longer show
the building as it is. The older keyframes are those the map's ghosts hold (made by earlier
missions, or in this one by a robot since lost); each new keyframe of a placed robot is
compared with them, by two rules:

1. **Superseded**: an older keyframe within ``known_map.supersede_m`` of the new one, of
   whose returns the new one's beams reach at least ``COVER`` (they end there or beyond: the
   new view sees what the older saw, or sees through it), is retired: the newer view replaces
   it. Where robots pass again the map keeps about one keyframe per place, so it does not
   grow from mission to mission.
2. **Changed**: a cell the map shows open where a new keyframe has a return (a door closed, a
   box brought in), or one it shows occupied that a new keyframe's beam passes through (a
   door opened, a box taken away), gets a vote; a cell with votes from
   ``known_map.change_votes`` keyframes over ``CHANGE_SPAN_S`` at least, with ``SUPPORT``
   other such cells within ``SUPPORT_M`` (a change is a stretch of wall that stays, not one
   stray return; a new wall a later beam passes through was a robot or a person that moved
   on, and its votes are dropped), is a change. The older keyframes that
   contradict it are retired: those whose beams passed through a new wall, those with a
   return on a wall that is gone. What they alone showed elsewhere becomes unknown again, for
   the team to explore.

Retired keyframes stay in the graph (held by their priors, they move nothing) and out of the
map drawn and the map left for the next mission. Retirements are applied together at most
every ``APPLY_S`` (each makes the team's map be drawn again). A robot found lost gives back
what its keyframes since it went astray retired. No I/O here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import inverse, transform_points
from server.fleet.model import Fleet, RobotContext
from server.knownmap.config import KnownMapConfig
from server.knownmap.mapdata import KnownMap, harvest
from server.rendezvous.mapmatch import Layers, _cells
from server.slam.keyframes import Keyframe

F64 = NDArray[np.float64]

#: share of an older keyframe's returns a newer one's beams must reach to supersede it
COVER = 0.8
#: how far short of a return a beam may end and still reach it [m]
REACH_TOL_M = 0.15
#: bearing bins of a keyframe's beams (half a degree)
BINS = 720
#: the keyframes that vote a cell changed must span this long [s] (what moves on, a robot or
#: a person, is seen through meanwhile and its votes dropped)
CHANGE_SPAN_S = 4.0
#: confirmed cells of the same kind a changed cell needs within ``SUPPORT_M``
SUPPORT, SUPPORT_M = 4, 0.3
#: an older keyframe's place is inspected once a new keyframe is this near it [m]
INSPECT_M = 1.5
#: changed cells an older keyframe must contradict to be retired
CONTRA = 3
#: keyframes of one mission this near each other are of one place (``slam.keyframes``' spacing)
SAME_MISSION_M = 0.5
#: retirements are applied (the map drawn again) at most this often [s]
APPLY_S = 2.0
#: an older return is gone when the new beams toward it (nearer than this, [m]) pass it by
#: this much [m]
PASS_FROM_M, PASS_MARGIN_M = 0.3, 0.3


def beams(kf: Keyframe) -> F64:
    """A keyframe's beams by bearing (``BINS``): how far each reached (a return or the end of
    an empty beam), NaN where it had none; each bin the farthest of it and its neighbours."""
    pts = np.asarray(kf.render.stored(), dtype=np.float64)
    out = np.full(BINS, np.nan)
    if not len(pts):
        return out
    b = _bins(np.arctan2(pts[:, 1], pts[:, 0]))
    np.fmax.at(out, b, np.hypot(pts[:, 0], pts[:, 1]))
    return out


def _bins(bearing: F64) -> NDArray[np.int64]:
    return (np.floor((bearing + math.pi) / (2 * math.pi) * BINS).astype(np.int64)) % BINS


def reach(prof: F64, T_kf: F64, xy: F64) -> tuple[F64, F64]:
    """For points in the map frame: their distance from the keyframe at ``T_kf``, and how far
    its beams toward them reached (the farthest of the nearest three bins; NaN: no beam)."""
    q = transform_points(inverse(T_kf), xy)
    b = _bins(np.arctan2(q[:, 1], q[:, 0]))
    near = np.stack([prof[(b + s) % BINS] for s in (-1, 0, 1)])
    ok = np.isfinite(near).any(axis=0)
    r = np.full(len(b), np.nan)
    r[ok] = np.nanmax(near[:, ok], axis=0)
    return np.hypot(q[:, 0], q[:, 1]), r


@dataclass
class Old:
    """The older keyframes (the map ghosts'), not retired: who holds each, and where."""

    owners: list[tuple[str, int]]
    poses: F64


@dataclass
class Upkeep:
    """The votes and retirements of one mission (see the module docstring)."""

    k: KnownMapConfig
    seen: dict[str, int] = field(default_factory=dict)        # robot -> keyframes compared
    #: cell -> (keyframes that saw it changed, the first one's stamp)
    votes: dict[tuple[str, int, int], tuple[int, int]] = field(default_factory=dict)
    confirmed: dict[tuple[str, int, int], int] = field(default_factory=dict)  # -> applied?
    pending: list[tuple[str, int, str, int, str]] = field(default_factory=list)
    #: robot -> (its keyframe, ghost, ghost's keyframe) retired because of it
    retired_by: dict[str, list[tuple[int, str, int]]] = field(default_factory=dict)
    applied_ns: int = 0
    fresh: list[F64] = field(default_factory=list)      # changed cells not yet reported
    claimed: list[tuple[float, float]] = field(default_factory=list)   # inspection goals
    inspected: bool = False
    counts: dict[str, int] = field(default_factory=lambda: {
        "superseded": 0, "contradicted": 0, "changed_cells": 0})
    _cache: dict[tuple[str, int], tuple[F64, F64]] = field(default_factory=dict)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_cache": {}}      # made again on demand

    # -- per keyframe ------------------------------------------------------------------------
    def on_scan(self, fleet: Fleet, team_id: str, r: RobotContext, lay: Layers) -> None:
        """Compare ``r``'s keyframes not compared yet with the older ones and the map."""
        n = len(r.slam.keyframes)
        start = self.seen.get(r.robot_id, 0)
        if n <= start or r.unmapped:
            return
        self.seen[r.robot_id] = n
        old = self._old(fleet, team_id)
        for k in range(start, n):
            kf, T = r.slam.keyframes[k], r.slam.keyframe_pose(k)
            prof = beams(kf)
            self._supersede(fleet, r.robot_id, k, T, prof, old)
            self._vote(fleet, kf, T, prof, old, lay)
        self._contradict(fleet, r.robot_id, n - 1, old, lay)

    def _old(self, fleet: Fleet, team_id: str) -> Old:
        owners: list[tuple[str, int]] = []
        poses = []
        taken = {(g, i) for _, _, g, i, _ in self.pending}
        for rid in fleet.teams[team_id].robot_ids:
            g = fleet.robots[rid]
            if not g.ghost or g.unmapped:
                continue
            P = g.slam.keyframe_poses()
            for i in range(len(g.slam.keyframes)):
                if i not in g.retired and (rid, i) not in taken:
                    owners.append((rid, i))
                    poses.append(P[i])
        return Old(owners, np.array(poses).reshape(-1, 3))

    def _hits(self, fleet: Fleet, gid: str, i: int) -> tuple[F64, F64]:
        """An older keyframe's returns in the map frame, and its beams (cached)."""
        c = self._cache.get((gid, i))
        if c is None:
            g = fleet.robots[gid]
            kf = g.slam.keyframes[i]
            c = self._cache[(gid, i)] = (
                transform_points(g.slam.keyframe_pose(i), np.asarray(kf.hits, np.float64)),
                beams(kf))
        return c

    def _supersede(self, fleet: Fleet, rid: str, k: int, T: F64, prof: F64, old: Old) -> None:
        if self.k.supersede_m <= 0 or not len(old.poses):
            return
        d = np.hypot(*(old.poses[:, :2] - T[:2]).T)
        for j in np.flatnonzero(d <= self.k.supersede_m):
            gid, i = old.owners[j]
            xy, _ = self._hits(fleet, gid, i)
            if not len(xy):
                continue
            dist, got = reach(prof, T, xy)
            if np.mean(np.isfinite(got) & (got >= dist - REACH_TOL_M)) >= COVER:
                self.pending.append((rid, k, gid, i, "superseded"))

    def _vote(self, fleet: Fleet, kf: Keyframe, T: F64, prof: F64, old: Old,
              lay: Layers) -> None:
        step = lay.fine_m
        hits = transform_points(T, np.asarray(kf.hits, np.float64))
        i, j, ok = _cells(lay, hits)
        new_wall = np.zeros(len(hits), dtype=bool)
        new_wall[ok] = lay.fine_clear[i[ok], j[ok]]
        found = [("wall", hits[new_wall])]
        # the older keyframes' returns the new beams pass well beyond (each of the three
        # nearest: a beam grazing a wall that is still there has a neighbour short of it)
        span = float(np.nanmax(prof, initial=0.0))
        near = np.hypot(*(old.poses[:, :2] - T[:2]).T) <= span if len(old.poses) else []
        for jj in np.flatnonzero(near):
            xy, _ = self._hits(fleet, *old.owners[jj])
            if not len(xy):
                continue
            q = transform_points(inverse(T), xy)
            dist = np.hypot(q[:, 0], q[:, 1])
            b = _bins(np.arctan2(q[:, 1], q[:, 0]))
            short = np.min(np.stack([prof[(b + s) % BINS] for s in (-1, 0, 1)]), axis=0)
            gone = np.isfinite(short) & (short > dist + PASS_MARGIN_M) & (dist >= PASS_FROM_M)
            found.append(("gone", xy[gone]))
        cells = {(kind, int(r), int(c)) for kind, xy in found
                 for c, r in np.floor(xy / step).astype(np.int64)}
        self._clear(T, prof, step, cells)
        for key in cells:           # keyed by place, not by the view's cells
            n, first = self.votes.get(key, (0, kf.stamp_ns))
            self.votes[key] = (n + 1, first)
            if n + 1 >= self.k.change_votes and kf.stamp_ns - first >= CHANGE_SPAN_S * 1e9:
                self.confirmed.setdefault(key, 0)

    def _clear(self, T: F64, prof: F64, step: float, cells: set[tuple[str, int, int]]) -> None:
        """New walls the keyframe's beams pass through (not among its ``cells``) were
        something that moved on (a robot, a person): their votes are dropped."""
        keys = [key for key in self.votes if key[0] == "wall" and key not in cells
                and not self.confirmed.get(key, 0)]
        if not keys:
            return
        xy = np.array([((c + 0.5) * step, (r + 0.5) * step) for _, r, c in keys])
        dist, got = reach(prof, T, xy)
        for key, through in zip(keys, np.isfinite(got) & (got > dist + REACH_TOL_M),
                                strict=True):
            if through:
                del self.votes[key]
                self.confirmed.pop(key, None)

    def changed_xy(self, kind: str, step: float, fresh: bool = False) -> F64:
        """Centres of confirmed changed cells of ``kind`` (cells of ``step``) with enough
        support; ``fresh``: only those not yet acted on, which are then marked so."""
        keys = [key for key in self.confirmed if key[0] == kind]
        if not keys:
            return np.zeros((0, 2))
        xy = np.array([((c + 0.5) * step, (r + 0.5) * step) for _, r, c in keys])
        d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
        keep = (d <= SUPPORT_M).sum(axis=1) - 1 >= SUPPORT
        if fresh:
            keep &= np.array([self.confirmed[key] == 0 for key in keys])
            for key, kept in zip(keys, keep, strict=True):
                if kept:
                    self.confirmed[key] = 1
        return xy[keep]

    def _contradict(self, fleet: Fleet, rid: str, k: int, old: Old, lay: Layers) -> None:
        walls = self.changed_xy("wall", lay.fine_m, True)
        gone = self.changed_xy("gone", lay.fine_m, True)
        if not (len(walls) or len(gone)):
            return
        self.counts["changed_cells"] += len(walls) + len(gone)
        self.fresh += [walls, gone]
        for gid, i in old.owners:
            xy, prof = self._hits(fleet, gid, i)
            T = fleet.robots[gid].slam.keyframe_pose(i)
            hit = False
            if len(walls):          # its beams passed through where a wall now is
                dist, got = reach(prof, T, walls)
                hit = int((np.isfinite(got) & (got > dist + REACH_TOL_M)).sum()) >= CONTRA
            if not hit and len(gone) and len(xy):   # it saw a wall that is gone
                d = np.hypot(xy[:, None, 0] - gone[None, :, 0], xy[:, None, 1] - gone[None, :, 1])
                hit = int((d.min(axis=0) <= 1.5 * lay.fine_m).sum()) >= CONTRA
            if hit:
                self.pending.append((rid, k, gid, i, "contradicted"))

    # -- the pass over the map ---------------------------------------------------------------
    def inspect_goal(self, fleet: Fleet, team_id: str, r: RobotContext
                     ) -> tuple[float, float] | None:
        """The nearest of the older keyframes' places no new keyframe (nor a robot sent
        there) has come within ``INSPECT_M`` of; None once ``known_map.inspected_share`` of
        them has been (the pass is over: the team explores what is unknown)."""
        if self.inspected:
            return None
        old = self._old(fleet, team_id)
        if not len(old.poses):
            return None
        xy = old.poses[:, :2]
        team = fleet.teams[team_id]
        new = [fleet.robots[rid].slam.keyframe_poses()[:, :2] for rid in team.robot_ids
               if not fleet.robots[rid].ghost and fleet.robots[rid].slam.keyframes]
        near = np.vstack([np.zeros((0, 2)), *new, np.array(self.claimed).reshape(-1, 2)])
        seen = np.zeros(len(xy), dtype=bool)
        for q in near:
            seen |= np.hypot(xy[:, 0] - q[0], xy[:, 1] - q[1]) <= INSPECT_M
        # the retired ones were seen again too
        share = (seen.sum() + sum(len(g) for g in self.retired_by.values())) / \
            (len(xy) + sum(len(g) for g in self.retired_by.values()))
        if seen.all() or share >= self.k.inspected_share:
            self.inspected = True
            return None
        d = np.hypot(xy[:, 0] - r.pose[0], xy[:, 1] - r.pose[1])
        d[seen] = np.inf
        x, y = xy[int(np.argmin(d))]
        self.claimed.append((float(x), float(y)))
        return float(x), float(y)

    # -- applying ----------------------------------------------------------------------------
    def apply(self, fleet: Fleet, now_ns: int) -> tuple[dict[str, int], list[F64]] | None:
        """Retire what is pending, if ``APPLY_S`` has passed since the last time: how many
        by each rule, and the changed regions found since (each its changed cells' centres);
        None: nothing applied."""
        if not self.pending or now_ns - self.applied_ns < APPLY_S * 1e9:
            return None
        self.applied_ns = now_ns
        regions = _regions(np.vstack([np.zeros((0, 2)), *self.fresh]))
        self.fresh = []
        done = {"superseded": 0, "contradicted": 0}
        for rid, k, gid, i, why in self.pending:
            g = fleet.robots.get(gid)
            if g is None or i in g.retired:
                continue
            g.retired.add(i)
            self.retired_by.setdefault(rid, []).append((k, gid, i))
            self._cache.pop((gid, i), None)
            done[why] += 1
            self.counts[why] += 1
        self.pending = []
        return (done, regions) if any(done.values()) or regions else None

    def forget(self, fleet: Fleet, rid: str, kept: int) -> int:
        """``rid`` is lost: what its keyframes from ``kept`` on retired is drawn again, and its
        new keyframes are compared from its first. Returns how many were given back."""
        self.pending = [p for p in self.pending if not (p[0] == rid and p[1] >= kept)]
        back = [t for t in self.retired_by.get(rid, []) if t[0] >= kept]
        self.retired_by[rid] = [t for t in self.retired_by.get(rid, []) if t[0] < kept]
        for _, gid, i in back:
            g = fleet.robots.get(gid)
            if g is not None:
                g.retired.discard(i)
        self.seen[rid] = 0
        return len(back)


def consolidated(known: KnownMap, supersede_m: float) -> tuple[KnownMap, int]:
    """The map a mission leaves, its keyframes that newer ones see again dropped: the rule
    of superseding (``COVER``, within ``supersede_m``), the newest first (by mission, then
    stamp), among this mission's keyframes within ``SAME_MISSION_M`` (its robots passing the
    same place again leave one) and between missions (an earlier one's for a later one's).
    Returns the map and how many were dropped."""
    if supersede_m <= 0 or len(known) < 2:
        return known, 0

    def mission_of(source: str) -> int:
        head = source.split(":", 1)[0]
        return int(head) if head.isdigit() else 0

    missions = [mission_of(s) for s in known.sources]
    last = max(missions)
    order = sorted(range(len(known)), key=lambda k: (missions[k], known.keyframes[k].stamp_ns),
                   reverse=True)
    kept: list[int] = []
    profs: dict[int, F64] = {}
    for k in order:
        kf, T = known.keyframes[k], known.poses[k]
        # a keyframe of an earlier mission goes for a later one's; this mission's keep one
        # per place as one robot's keyframes do (their spacing); earlier missions' own are
        # left as those missions left them
        near = [q for q in kept if math.hypot(*(known.poses[q, :2] - T[:2])) <= (
            supersede_m if missions[q] > missions[k] else
            min(supersede_m, SAME_MISSION_M) if missions[k] == last else -1.0)]
        xy = transform_points(T, np.asarray(kf.hits, np.float64)) if near else np.zeros((0, 2))
        covered = False
        for q in near:
            if q not in profs:
                profs[q] = beams(known.keyframes[q])
            dist, got = reach(profs[q], known.poses[q], xy)
            if len(xy) and np.mean(np.isfinite(got) & (got >= dist - REACH_TOL_M)) >= COVER:
                covered = True
                break
        if not covered:
            kept.append(k)
    keep = sorted(kept)
    if len(keep) == len(known):
        return known, 0
    out = harvest([([known.sources[k] for k in keep], [known.keyframes[k] for k in keep],
                    known.poses[keep])], known.resolution_m, known.anchor, known.missions,
                  known.notes)
    return out, len(known) - len(keep)


def _regions(xy: F64, apart_m: float = 0.5) -> list[F64]:
    """Points grouped into regions: those nearer than ``apart_m``, one after another."""
    if not len(xy):
        return []
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(xy).query_pairs(apart_m, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(xy),) * 2)
    _, label = connected_components(g, directed=False)
    return [xy[label == c] for c in range(int(label.max()) + 1)]
