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
   box brought in), or where an older return lies that the new beams pass well beyond (a
   door opened, a box taken away), gets a vote; a cell with votes from
   ``known_map.change_votes`` keyframes over ``CHANGE_SPAN_S`` at least, the first and the
   confirming one ``VIEWS_APART_M`` apart (two views, not one robot's while it stood), with
   ``SUPPORT``
   other such cells within ``SUPPORT_M`` (a change is a stretch of wall that stays, not one
   stray return; a new wall a later beam passes through was a robot or a person that moved
   on, and its votes are dropped), is a change. A return within the footprint of a robot
   of the team, where it stands when the keyframe is compared, is that robot: no vote.
   The older keyframes that contradict it are
   cut (``trimmed``): their beams through a new wall, their returns on a wall that is gone,
   are dropped from what the map is drawn from; the rest of what they show stays.

Retired keyframes stay in the graph (held by their priors, they move nothing) and out of the
map drawn and the map left for the next mission; cut ones are written cut. Both are applied
together at most every ``APPLY_S`` (each makes the team's map be drawn again). A robot found
lost gives back what its keyframes since it went astray retired or cut. No I/O here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import inverse, transform_points
from server.fleet.model import Fleet, RobotContext
from server.knownmap.config import KnownMapConfig
from server.knownmap.sweep import URGENT, Sweep
from server.knownmap.views import BINS, COVER, REACH_TOL_M, _bins, beams, reach
from server.rendezvous.mapmatch import Layers, _cells
from server.slam.keyframes import Keyframe
from server.slam.render_store import RenderScan

F64 = NDArray[np.float64]

#: the keyframes that vote a cell changed must span this long [s] (what moves on, a robot or
#: a person, is seen through meanwhile and its votes dropped)
CHANGE_SPAN_S = 4.0
#: ... and the first and the confirming keyframe must stand this far apart [m]: two views
#: of it, not one robot's view while it stood
VIEWS_APART_M = 1.0
#: a new return this near a robot of the team (its footprint: its radius and this margin,
#: where it stands when the scan is compared) is that robot, never a change [m]
BODY_MARGIN_M = 0.15
#: confirmed cells of the same kind a changed cell needs within ``SUPPORT_M``
SUPPORT, SUPPORT_M = 4, 0.3
#: a new return is on the map's open floor only this far from every wall the map shows [m]:
#: an earlier mission's map is some centimetres off here and there
WALL_GAP_M = 0.3
#: beams an older keyframe must have through changed cells to be cut; a beam passing this
#: many cells from a changed cell's centre passes through it
CONTRA, CROSS_CELLS = 3, 0.75
#: retirements are applied (the map drawn again) at most this often [s]
APPLY_S = 2.0
#: an older return is gone when the new beams toward it (nearer than this, [m]) pass it by
#: this much [m]
PASS_FROM_M, PASS_MARGIN_M = 0.3, 0.3


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
    #: cell -> (keyframes that saw it changed, the first one's stamp, x, y)
    votes: dict[tuple[str, int, int], tuple[int, int, float, float]] = field(
        default_factory=dict)
    confirmed: dict[tuple[str, int, int], int] = field(default_factory=dict)  # -> applied?
    step_m: float = 0.0                         # the side of the cells voted for [m]
    pending: list[tuple[str, int, str, int, str]] = field(default_factory=list)
    #: robot -> (its keyframe, ghost, ghost's keyframe) retired because of it
    retired_by: dict[str, list[tuple[int, str, int]]] = field(default_factory=dict)
    #: older keyframes cut to what the changes leave true: (robot, its keyframe, ghost,
    #: ghost's keyframe, the keyframe cut), to apply; those applied, by robot; the originals
    trims: list[tuple[str, int, str, int, Keyframe]] = field(default_factory=list)
    trimmed_by: dict[str, list[tuple[int, str, int]]] = field(default_factory=dict)
    originals: dict[tuple[str, int], Keyframe] = field(default_factory=dict)
    applied_ns: int = 0
    fresh: list[F64] = field(default_factory=list)      # changed cells not yet reported
    sweep: Sweep = field(default_factory=Sweep)                        # the pass
    inspected: bool = False
    counts: dict[str, int] = field(default_factory=lambda: {
        "superseded": 0, "trimmed": 0, "changed_cells": 0})
    _cache: dict[tuple[str, int], tuple[F64, F64]] = field(default_factory=dict)
    _far: tuple[Layers, NDArray[np.bool_]] | None = None
    _unconf: tuple[F64, F64] | None = None      # ``_unconfirmed``, until the votes change

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_cache": {}, "_far": None,       # made again on demand
                "_unconf": None}

    def _open(self, lay: Layers) -> NDArray[np.bool_]:
        """The map's open floor ``WALL_GAP_M`` or more from every wall it shows (a return
        there is a new wall; nearer, it may be a wall the older map drew a little off)."""
        if self._far is None or self._far[0] is not lay:
            from scipy.ndimage import binary_dilation
            n = max(2, int(np.ceil(WALL_GAP_M / lay.fine_m)))
            yy, xx = np.mgrid[-n:n + 1, -n:n + 1]
            near = binary_dilation(lay.fine_occ, structure=xx ** 2 + yy ** 2 <= n * n)
            self._far = (lay, lay.fine_clear & ~near)
        return self._far[1]

    # -- per keyframe ------------------------------------------------------------------------
    def on_scan(self, fleet: Fleet, team_id: str, r: RobotContext, lay: Layers) -> None:
        """Compare ``r``'s keyframes not compared yet with the older ones and the map."""
        n = len(r.slam.keyframes)
        start = self.seen.get(r.robot_id, 0)
        if n <= start or r.unmapped:
            return
        self.seen[r.robot_id] = n
        old = self._old(fleet, team_id)
        bodies = _bodies(fleet, team_id, r)
        for k in range(start, n):
            kf, T = r.slam.keyframes[k], r.slam.keyframe_pose(k)
            prof = beams(kf)
            self._supersede(fleet, r.robot_id, k, T, prof, old)
            self.sweep.start(old.owners, self._xy(fleet))
            self.sweep.saw(prof, T)
            self._vote(fleet, kf, T, prof, old, lay, bodies)
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
              lay: Layers, bodies: F64 | None = None) -> None:
        """The cells ``kf`` (at ``T``) sees changed get its vote; its returns within
        ``bodies`` (the team's robots: (x, y, radius)) are robots, not walls."""
        step = self.step_m = lay.fine_m
        self._unconf = None             # the votes change
        hits = transform_points(T, np.asarray(kf.hits, np.float64))
        i, j, ok = _cells(lay, hits)
        new_wall = np.zeros(len(hits), dtype=bool)
        new_wall[ok] = self._open(lay)[i[ok], j[ok]]
        if bodies is not None and len(bodies) and len(hits):
            d = np.hypot(hits[:, None, 0] - bodies[None, :, 0],
                         hits[:, None, 1] - bodies[None, :, 1])
            new_wall &= ~(d <= bodies[None, :, 2]).any(axis=1)
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
        x, y = float(T[0]), float(T[1])
        for key in cells:           # keyed by place, not by the view's cells
            n, first, x0, y0 = self.votes.get(key, (0, kf.stamp_ns, x, y))
            self.votes[key] = (n + 1, first, x0, y0)
            if n + 1 >= self.k.change_votes and kf.stamp_ns - first >= CHANGE_SPAN_S * 1e9 \
                    and np.hypot(x - x0, y - y0) >= VIEWS_APART_M:
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
        r_m = CROSS_CELLS * lay.fine_m
        for gid, i in old.owners:
            g = fleet.robots[gid]
            kf, T = g.slam.keyframes[i], g.slam.keyframe_pose(i)
            pts = np.asarray(kf.render.stored(), dtype=np.float64)
            drop = np.zeros(len(pts), dtype=bool)
            if len(walls):          # its beams that passed where a wall now is
                c = transform_points(inverse(T), walls)
                rng = np.hypot(pts[:, 0], pts[:, 1])
                u = pts / np.maximum(rng, 1e-9)[:, None]
                t = u @ c.T                                     # (N, M) along each beam
                perp = np.abs(u[:, :1] * c[None, :, 1] - u[:, 1:] * c[None, :, 0])
                drop |= ((t > 0) & (t < rng[:, None] - REACH_TOL_M) & (perp <= r_m)).any(axis=1)
            if len(gone):           # its returns on a wall that is gone
                c = transform_points(inverse(T), gone)
                h = pts[:kf.render.n_hits]
                d = np.hypot(h[:, None, 0] - c[None, :, 0], h[:, None, 1] - c[None, :, 1])
                drop[:len(h)] |= d.min(axis=1) <= r_m
            if drop.sum() >= CONTRA:
                n = kf.render.n_hits
                keep = ~drop
                render = RenderScan.of(pts[:n][keep[:n]], pts[n:][keep[n:]])
                self.trims.append((rid, k, gid, i, Keyframe(kf.index, kf.stamp_ns,
                                                              kf.T_odom_robot, kf.matchable,
                                                              render)))

    # -- the pass over the map ---------------------------------------------------------------
    def inspect_goal(self, fleet: Fleet, team_id: str, r: RobotContext
                     ) -> tuple[float, float] | None:
        """The place of an older keyframe ``r`` goes to next on the pass over the map
        (``sweep.Sweep.goal``: most of what it saw not seen again, per metre of the way);
        None once the pass is over (the team explores what is unknown)."""
        if self.inspected:
            return None
        old = self._old(fleet, team_id)
        hits = self._xy(fleet)
        self.sweep.start(old.owners, hits)
        goal = None
        if self.sweep.share_seen() < self.k.inspected_share and len(old.poses):
            goal = self.sweep.goal(r.robot_id, r.pose, old.owners, old.poses[:, :2], hits)
        if goal is None and len(old.poses):
            # nothing left to see again, but a change seen by one view only: the pass goes
            # on to a place that sees it again, from elsewhere (else it would never show)
            goal = self.sweep.goal(r.robot_id, r.pose, old.owners, old.poses[:, :2], hits,
                                   urgent=self._confirming(fleet, old))
        if goal is None:
            self.inspected = True
        return goal

    def inspect_stale(self, fleet: Fleet, r: RobotContext) -> bool:
        """``r``'s place on the pass shows little not seen again by now (``Sweep.stale``);
        one it was sent to to see a change again, once it sees none left unconfirmed."""
        g = self.sweep.goals.get(r.robot_id)
        if g is not None and g[2] == URGENT:
            gid, i = g[0]
            ghost = fleet.robots.get(gid)
            return ghost is None or i in ghost.retired or not self._sees_unconfirmed(
                fleet, g[0], ghost.slam.keyframe_pose(i), self._unconfirmed())
        return self.sweep.stale(r.robot_id, self._xy(fleet))

    def _unconfirmed(self) -> tuple[F64, F64]:
        """The cells seen changed but not confirmed, in clusters of ``SUPPORT`` + 1 within
        ``SUPPORT_M`` (what a change needs): their centres, and where each was first seen
        (kept until a keyframe votes again)."""
        if self._unconf is None:
            self._unconf = self._clusters()
        return self._unconf

    def _clusters(self) -> tuple[F64, F64]:
        keys = [(key, v) for key, v in self.votes.items() if key not in self.confirmed]
        if not keys or self.step_m <= 0:
            return np.zeros((0, 2)), np.zeros((0, 2))
        xy = np.array([((c + 0.5) * self.step_m, (r + 0.5) * self.step_m)
                       for (_, r, c), _ in keys])
        first = np.array([(v[2], v[3]) for _, v in keys])
        d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
        keep = (d <= SUPPORT_M).sum(axis=1) - 1 >= SUPPORT
        return xy[keep], first[keep]

    def _sees_unconfirmed(self, fleet: Fleet, place: tuple[str, int], P: F64,
                          cells: tuple[F64, F64]) -> bool:
        """The older keyframe ``place`` (at ``P``) has beams that reached ``SUPPORT`` + 1 of
        ``cells`` (it saw open floor there, or the returns now gone), from ``VIEWS_APART_M``
        or more from where they were first seen: from there they are seen again, by another
        view."""
        xy, first = cells
        if not len(xy):
            return False
        apart = np.hypot(first[:, 0] - P[0], first[:, 1] - P[1]) >= VIEWS_APART_M
        if apart.sum() <= SUPPORT:
            return False
        _, prof = self._hits(fleet, *place)
        dist, got = reach(prof, P, xy[apart])
        return int((np.isfinite(got) & (got >= dist - REACH_TOL_M)).sum()) > SUPPORT

    def _confirming(self, fleet: Fleet, old: Old) -> list[int]:
        """The places (indices into ``old``) from which a change seen once is seen again."""
        cells = self._unconfirmed()
        if not len(cells[0]):
            return []
        return [j for j, place in enumerate(old.owners)
                if self._sees_unconfirmed(fleet, place, old.poses[j], cells)]

    def _xy(self, fleet: Fleet) -> Callable[[str, int], F64]:
        return lambda gid, i: self._hits(fleet, gid, i)[0]

    # -- applying ----------------------------------------------------------------------------
    def apply(self, fleet: Fleet, now_ns: int) -> tuple[dict[str, int], list[F64]] | None:
        """Retire what is pending, if ``APPLY_S`` has passed since the last time: how many
        by each rule, and the changed regions found since (each its changed cells' centres);
        None: nothing applied."""
        if not (self.pending or self.trims) or now_ns - self.applied_ns < APPLY_S * 1e9:
            return None
        self.applied_ns = now_ns
        regions = _regions(np.vstack([np.zeros((0, 2)), *self.fresh]))
        self.fresh = []
        done = {"superseded": 0, "trimmed": 0}
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
        for rid, k, gid, i, kf in self.trims:
            g = fleet.robots.get(gid)
            if g is None or i in g.retired:
                continue
            self.originals.setdefault((gid, i), g.slam.keyframes[i])
            g.slam.keyframes[i] = kf
            self.trimmed_by.setdefault(rid, []).append((k, gid, i))
            self._cache.pop((gid, i), None)
            done["trimmed"] += 1
            self.counts["trimmed"] += 1
        self.trims = []
        return (done, regions) if any(done.values()) or regions else None

    def forget(self, fleet: Fleet, rid: str, kept: int) -> int:
        """``rid`` is lost: what its keyframes from ``kept`` on retired is drawn again, and its
        new keyframes are compared from its first. Returns how many were given back."""
        self.pending = [p for p in self.pending if not (p[0] == rid and p[1] >= kept)]
        self.trims = [p for p in self.trims if not (p[0] == rid and p[1] >= kept)]
        cut = [t for t in self.trimmed_by.get(rid, []) if t[0] >= kept]
        self.trimmed_by[rid] = [t for t in self.trimmed_by.get(rid, []) if t[0] < kept]
        for _, gid, i in cut:
            g, kf = fleet.robots.get(gid), self.originals.pop((gid, i), None)
            if g is not None and kf is not None:
                g.slam.keyframes[i] = kf
                self._cache.pop((gid, i), None)
        back = [t for t in self.retired_by.get(rid, []) if t[0] >= kept]
        self.retired_by[rid] = [t for t in self.retired_by.get(rid, []) if t[0] < kept]
        for _, gid, i in back:
            g = fleet.robots.get(gid)
            if g is not None:
                g.retired.discard(i)
        self.seen[rid] = 0
        return len(back) + len(cut)


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


def _bodies(fleet: Fleet, team_id: str, r: RobotContext) -> F64:
    """Where the team's robots other than ``r`` stand now, each with its footprint's radius
    (``control.robot_radius_m`` + ``BODY_MARGIN_M``): (x, y, radius) rows."""
    radius = fleet.cfg.control.robot_radius_m + BODY_MARGIN_M
    rows = [(float(o.pose[0]), float(o.pose[1]), radius)
            for o in (fleet.robots[rid] for rid in fleet.teams[team_id].robot_ids)
            if o.robot_id != r.robot_id and not o.ghost and o.alive and o.scans]
    return np.array(rows, dtype=np.float64).reshape(-1, 3)
