"""Graph surgery: joining robots' graphs into a team's, tying them by map matches, and taking
tag sightings out once the maps tie a pair.

``join_graph`` builds a team's joint GTSAM problem: every member's factors (one prior: the
anchor's), the links between them, initial values in the anchor's frame; a batch optimisation
first, then ISAM2 carries on. ``GraphSurgery`` does the operations the merger and the per-scan
loop need on top of it, on the fleet's robots. No I/O here.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.noise import robust
from factors.rendezvous import rendezvous_factor
from factors.scan_match import loop_closure_factor, pose2, whitened_chi2
from schemas.se2 import compose, inverse
from server.config import ServerConfig
from server.fleet.model import Fleet, Link, RobotContext, Team
from server.rendezvous.counters import RendezvousCounters
from server.rendezvous.evidence import SightingRecord
from server.rendezvous.maps import cross_matches
from server.slam import RobotSlam
from server.slam.backend import FactorRecord, PoseGraph
from server.slam.frontend import is_narrow

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: how far from a robot's keyframe the keyframes of a known map (``server.knownmap``) are
#: matched against it (5 m between teams): the map may have seen the robot's room only from
#: its door
KNOWN_MAP_RADIUS_M = 8.0
#: a narrow robot's whole scans this close [m] to a wide teammate's new keyframe are matched
#: against its map (``GraphSurgery._tie_wholes``): what a LIDAR maps from there
WHOLE_TIE_RADIUS_M = 6.0
#: ... when that map shows this share of the whole scan's points (``seen_fraction``)
WHOLE_TIE_SEEN = 0.5
#: ... each at most this many times until one match holds it
WHOLE_TIE_TRIES = 3


def join_graph(members: Sequence[RobotSlam], anchor: RobotSlam,
               links: Iterable[FactorRecord], initial: dict[int, F64],
               relinearize_threshold: float) -> PoseGraph:
    """A new ISAM2 problem for ``members``: their factors (only ``anchor``'s prior), the
    rendezvous ``links``, solved in batch from ``initial`` (key -> pose in the team frame)."""
    records: list[FactorRecord] = []
    for m in members:
        for rec in m.trajectory.factors:
            if rec.kind == "prior" and m is not anchor:
                rec.index = None
                continue
            records.append(rec)
    records.extend(links)
    batch = gtsam.NonlinearFactorGraph()
    for rec in records:
        batch.add(rec.factor)
    values = gtsam.Values()
    for key, T in initial.items():
        values.insert(key, gtsam.Pose2(float(T[0]), float(T[1]), float(T[2])))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    est = gtsam.LevenbergMarquardtOptimizer(batch, values, params).optimize()
    graph = PoseGraph(relinearize_threshold)
    solved = {k: np.array([est.atPose2(k).x(), est.atPose2(k).y(), est.atPose2(k).theta()])
              for k in initial}
    idx = graph.add([r.factor for r in records], solved)
    for rec, i in zip(records, idx, strict=True):
        rec.index = i
    return graph


def team_initial_values(members_frames: Iterable[tuple[RobotSlam, F64]]) -> dict[int, F64]:
    """Current keyframe estimates of each robot moved into the team frame by its transform."""
    out: dict[int, F64] = {}
    for slam, T in members_frames:
        poses = slam.keyframe_poses()
        for k, P in zip(slam.trajectory.all_keys(), poses, strict=True):
            out[k] = compose(T, P)
    return out




class GraphSurgery:
    """Operations on the graphs of the fleet's robots (one thread)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, counters: RendezvousCounters) -> None:
        self.cfg, self.fleet, self.counters = cfg, fleet, counters
        #: per narrow robot, its whole scans' tries at a wide teammate's map (-1: tied)
        self._whole_tries: dict[str, dict[int, int]] = {}

    # -- links -----------------------------------------------------------------------------
    def sighting_link(self, rec: SightingRecord) -> Link:
        """A tag sighting as a robust rendezvous factor between the two robots' keyframes."""
        a, b = self.fleet.robots[rec.observer], self.fleet.robots[rec.observed]
        f = rendezvous_factor(a.slam.trajectory.key(rec.kf_a), b.slam.trajectory.key(rec.kf_b),
                              rec.sighting, rec.T_kf_a, rec.T_kf_b, kernel="huber")
        return Link(rec.observer, rec.observed, rec.stamp_ns, FactorRecord(f, "rendezvous"))

    def own_frames_link(self, a: str, b: str, T_own: F64, sigmas: F64, kind: str,
                        stamp_ns: int) -> tuple[F64, Link]:
        """A robust between-factor of the robots' first keyframes saying that b's own map
        frame is ``T_own`` in a's own map frame (known start poses, a marker measured by
        hand), and what it makes of the team transform (b's team frame -> a's)."""
        ra, rb = self.fleet.robots[a], self.fleet.robots[b]
        T_team = compose(compose(ra.own_frame_in_team(), T_own),
                         inverse(rb.own_frame_in_team()))
        T_link = compose(inverse(ra.slam.keyframe_pose(0)),
                         compose(T_team, rb.slam.keyframe_pose(0)))
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, dtype=np.float64))
        f = gtsam.BetweenFactorPose2(ra.slam.trajectory.key(0), rb.slam.trajectory.key(0),
                                     pose2(T_link), robust(noise, "huber"))
        return T_team, Link(a, b, stamp_ns, FactorRecord(f, kind))

    def add_link(self, team: Team, link: Link) -> None:
        """One more factor in a team's graph (a sighting between teammates)."""
        (link.record.index,) = self.fleet.robots[link.a].slam.graph.add([link.record.factor], {})
        team.links.append(link)

    # -- whole graphs ----------------------------------------------------------------------
    def rebuild(self, team: Team, frames: list[tuple[str, F64]], links: list[Link]) -> None:
        """One joint graph for ``frames`` (robot, transform of its current frame into the
        team's), anchored on ``team.anchor``, with ``links``; every robot continues in it."""
        robots = self.fleet.robots
        slams = [(robots[rid].slam, T) for rid, T in frames]
        graph = join_graph([sl for sl, _ in slams], robots[team.anchor].slam,
                           [ln.record for ln in links], team_initial_values(slams),
                           self.cfg.slam.graph.relinearize_threshold)
        for rid, _ in frames:
            r = robots[rid]
            r.slam.rebind(graph)
            r.pose = r.slam.pose
            r.nav.drop_target()
            r.look.forget()

    def _rebind(self, graph: PoseGraph, robots: Iterable[RobotContext]) -> None:
        for r in robots:
            r.slam.rebind(graph)
            r.pose = r.slam.pose
            r.obstacles = None   # kept in the frame the robot just left
            r.sighted = None

    # -- map matches -----------------------------------------------------------------------
    def match_teammates(self, r: RobotContext) -> None:
        """Every ``team_match_every`` new keyframes of a robot in a team of several (every whole
        scan of a narrow sensor's, ``_whole``): match the newest against its teammates' maps
        where they overlap. Without this, each robot's map
        would drift on its own after the merge, and the joint map would come apart where two
        robots went past the same walls at different times. A narrow robot's whole scan that
        sees one wall or a corridor is kept for its turn and its place across the walls
        (``cross_matches(hold_weak=True)``): a merge from tags leaves its map turned a degree
        or two, and it drives in corridors most."""
        every = self.cfg.teams.team_match_every
        team = self.fleet.team_of(r)
        k = len(r.slam.keyframes) - 1
        if every <= 0 or len(team.robot_ids) < 2:
            return
        if (not self._whole(r, k)) if r.slam.narrow else k % every:
            return
        mates = [o for o in team.robot_ids if o != r.robot_id]
        kept = self.refine_on_maps(mates, [r.robot_id], team.links, only=[k],
                                   hold_weak=r.slam.narrow)
        if not r.slam.narrow:
            kept += self._tie_wholes(r, mates, team.links)
        if kept and self.retire_sightings(team.links):
            team.links = [ln for ln in team.links if not ln.retired]

    def _tie_wholes(self, r: RobotContext, mates: list[str], links: list[Link]) -> int:
        """A wide robot's new keyframe maps a place its narrow teammates' whole scans may
        have seen before: each such whole scan within ``WHOLE_TIE_RADIUS_M`` of it, not yet
        tied to a wide teammate's map, is matched against that map now, where the map shows
        at least ``WHOLE_TIE_SEEN`` of it (at most ``WHOLE_TIE_TRIES`` such times). The
        narrow robot's keyframes from before the merge, or from rooms its teammate had not
        yet seen, are then held to the team's reference map, not only to its own drifting
        chain; its start too, which places its whole map."""
        P = r.slam.keyframe_pose(len(r.slam.keyframes) - 1)
        kept = 0
        for m in mates:
            mate = self.fleet.robots[m].slam
            if not mate.narrow or not mate.keyframes:
                continue
            tries = self._whole_tries.setdefault(m, {})
            poses = mate.keyframe_poses()
            near = np.flatnonzero(np.hypot(*(poses[:, :2] - P[:2]).T) <= WHOLE_TIE_RADIUS_M)
            todo = [int(i) for i in near if 0 <= tries.get(int(i), 0) < WHOLE_TIE_TRIES
                    and self._whole(self.fleet.robots[m], int(i))]
            if not todo:
                continue
            for i in todo:
                tried = [0]
                got = self.refine_on_maps([r.robot_id], [m], links, only=[i], tried=tried,
                                          min_seen_fraction=WHOLE_TIE_SEEN)
                kept += got
                if got:
                    tries[i] = -1
                elif tried[0]:      # the map showed what it saw, and it did not match
                    tries[i] = tries.get(i, 0) + 1
        return kept

    @staticmethod
    def _whole(r: RobotContext, k: int) -> bool:
        """Whether keyframe ``k`` of a narrow sensor's robot is a whole scan (its turning
        camera's views taken standing still, ``server.slam.sweep``): 360° and exact, each
        one is matched against its teammates' maps, and only these. A narrow view's match
        (18 points of one wall, in one run) moved the camera robot 0.5 m."""
        return r.slam.narrow and not is_narrow(r.slam.keyframes[k].matchable,
                                               r.slam.cfg.matcher)

    def refine_on_maps(self, side_a: list[str], side_b: list[str], links: list[Link],
                       only: list[int] | None = None, tried: list[int] | None = None,
                       min_seen_fraction: float = 0.0, hold_weak: bool = False) -> int:
        """Match each joining robot's keyframes (or the ones in ``only``) against the other
        side's map where they overlap, and add the matches as robust between-factors (``links``
        gets them); those still inconsistent after optimisation are taken out. Returns how
        many were kept."""
        if not self.cfg.teams.refine_on_maps:
            return 0
        g, loop = self.cfg.slam.graph, self.cfg.slam.loop
        floor = np.array([g.match_sigma_floor_m, g.match_sigma_floor_m,
                          math.radians(g.match_sigma_floor_deg)])
        added: list[Link] = []
        graph = None
        for ra in side_a:
            for rb in side_b:
                a, b = self.fleet.robots[ra].slam, self.fleet.robots[rb].slam
                graph = a.graph
                for m in cross_matches(a, b, only=only, radius_m=self._radius_m(ra),
                                       tried=tried, min_seen_fraction=min_seen_fraction,
                                       hold_weak=hold_weak):
                    f = loop_closure_factor(a.trajectory.key(m.ka), b.trajectory.key(m.kb),
                                            m.T_ka_kb, m.information, loop.sigma_scale ** 2,
                                            floor, "huber", loop.huber_k)
                    # one wall's match ties the maps across it only: it does not count
                    # toward retiring the sightings (``tied_by_maps``)
                    rec = FactorRecord(f, "cross_weak" if m.weak else "cross")
                    (rec.index,) = graph.add([f], {})
                    added.append(Link(ra, rb, 0, rec))
        if graph is None or not added:
            return 0
        graph.iterate(g.extra_iterations_after_loop)
        est = graph.estimate()
        bad = [ln for ln in added if whitened_chi2(ln.record.factor, est) > loop.max_chi2]
        if bad:
            graph.remove([ln.record.index for ln in bad if ln.record.index is not None])
            graph.iterate(g.extra_iterations_after_loop)
        kept = [ln for ln in added if ln not in bad]
        links.extend(kept)
        self._rebind(graph, (self.fleet.robots[rid] for rid in side_a + side_b))
        self.counters.map_matches += len(kept)
        return len(kept)

    def _radius_m(self, robot_id: str) -> float:
        """How far from a keyframe the keyframes of ``robot_id`` are matched against it."""
        team = self.fleet.teams.get(self.fleet.robots[robot_id].team_id)
        return KNOWN_MAP_RADIUS_M if team is not None and team.known else 5.0

    def tied_by_maps(self, links: list[Link], a: str, b: str) -> bool:
        """Whether map matches join robots a and b's graphs often enough that the tag
        sightings between them no longer count (``teams.retire_sightings_after``)."""
        need = self.cfg.teams.retire_sightings_after
        return need > 0 and sum(ln.record.kind == "cross" and {ln.a, ln.b} == {a, b}
                                for ln in links) >= need

    def retire_sightings(self, links: list[Link]) -> int:
        """Take the tag sightings out of the graph for every robot pair the maps now tie
        (``tied_by_maps``); they are marked ``retired`` (the caller drops them from the
        team's links). A meeting's sightings share their error (one geometry, seen from one
        place): kept beside map matches, they hold the two maps a fraction of a degree off
        where the robots met while the matches elsewhere pull them right, and both maps bend.
        Returns how many were taken out."""
        out = [ln for ln in links if ln.record.kind == "rendezvous" and not ln.retired
               and self.tied_by_maps(links, ln.a, ln.b)]
        if not out:
            return 0
        graph = self.fleet.robots[out[0].a].slam.graph
        graph.remove([ln.record.index for ln in out if ln.record.index is not None])
        for ln in out:
            ln.retired, ln.record.index = True, None
        graph.iterate(self.cfg.slam.graph.extra_iterations_after_loop)
        self._rebind(graph, (rc for rc in self.fleet.robots.values() if rc.slam.graph is graph))
        self.counters.sightings_retired += len(out)
        log.info("%d tag sightings left the graph: the maps tie %s", len(out),
                 ", ".join(sorted({"+".join(sorted((ln.a, ln.b))) for ln in out})))
        return len(out)

    def maps_still_match(self, side_a: list[str], side_b: list[str]) -> bool:
        """Whether keyframes of one side still match the other side's map (within 0.5 m)
        where they overlap, in the joint estimate."""
        tried = [0]
        robots = self.fleet.robots
        found = sum(len(cross_matches(robots[a].slam, robots[b].slam, tried=tried))
                    for a in side_a for b in side_b)
        return tried[0] >= self.cfg.teams.min_map_match_tries and \
            found >= max(1, tried[0] // 4)
