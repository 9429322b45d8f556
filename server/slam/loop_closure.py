"""Loop closure: candidates from the current estimate and its uncertainty, verified by matching
recent keyframes against older submaps.

- Submaps are blocks of consecutive keyframes, fixed in the frame of their middle keyframe
  (the anchor) once the block is complete.
- The uncertainty of the current pose relative to a submap grows with the distance travelled
  between them along the best-connected path of the graph (loop edges count as short), so
  the search window is ``r = r0 + α·D`` (capped): after long exploration the window is wide
  enough for the drift, right after a closure it is small.
- Verification: branch-and-bound correlative search in the window (global within it), then
  point-to-line ICP; a match must score high, have enough inliers and not be degenerate.
  A closure that would move the robot by more than ``confirm_correction_m`` must score at
  least ``confirm_min_score`` and waits until a second one agrees with it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, inverse, pose_distance
from server.slam.config import LoopClosureConfig
from server.slam.correlative import LikelihoodField, search
from server.slam.field_cache import FIELDS, new_owner
from server.slam.icp import IcpParams, MatchResult, PointMap, icp
from server.slam.keyframes import Keyframe, points_in_frame, voxel_thin
from server.slam.loop_kernel import relax

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
FIELD_CACHE = 24                 # likelihood fields kept (the submaps searched most lately) ...
FIELD_CACHE_BYTES = 8 << 20      # ... within this many bytes (each is 8 levels of float32), and
                                 # within the process's bound for all robots (``field_cache``)
LOOP_EDGE_LENGTH_M = 0.1


def edge_length_m(T_i_j: F64) -> float:
    """Length of the path-graph edge between two keyframes ``T_i_j`` apart: the distance [m]
    plus 0.2 m per radian turned."""
    d, a = pose_distance(T_i_j)
    return d + 0.2 * a


@dataclass
class Submap:
    """Keyframes ``members`` in the frame of keyframe ``anchor``. Its points are indexed for
    ICP (``PointMap``) only when a search verifies a closure on it: a long log holds
    thousands of submaps, and the index of each would stay for the whole run."""

    anchor: int
    members: list[int]
    points: F64
    normals: F64


@dataclass(frozen=True)
class LoopClosure:
    """A verified constraint ``T_anchor_kf`` between keyframes ``anchor`` and ``keyframe``."""

    anchor: int
    keyframe: int
    T_anchor_kf: F64
    information: F64
    score: float
    correction_m: float


@dataclass
class LoopStats:
    searches: int = 0
    candidates: int = 0
    accepted: int = 0
    rejected_score: int = 0
    rejected_icp: int = 0
    rejected_degenerate: int = 0
    rejected_ambiguous: int = 0
    rejected_weak: int = 0           # a large correction scoring under confirm_min_score
    pending: int = 0
    rejected_unconfirmed: int = 0
    removed_inconsistent: int = 0


class _Graph:
    """Path lengths in a keyframe chain with shortcut edges (loop closures).

    Keyframe i sits at arc length c_i along the chain. The shortest path from k is found by
    relaxing D ← min(D, D[a] + w + |c − c_b|) over the shortcut edges (a, b, w) in both
    directions until nothing changes (Bellman–Ford on the few extra edges; the chain itself is
    the |c − c_k| term).
    """

    def __init__(self) -> None:
        self.arc = np.zeros(1)
        self.shortcuts: list[tuple[int, int, float]] = []

    def add_edge(self, i: int, j: int, length_m: float) -> None:
        if j == i + 1 and j == len(self.arc):
            self.arc = np.append(self.arc, self.arc[-1] + length_m)
        else:
            self.shortcuts.append((i, j, length_m))

    def distances_from(self, source: int, n: int) -> F64:
        """Path lengths from ``source`` to keyframes 0..n-1 (inf where not connected)."""
        m = len(self.arc)
        dist = np.full(n, np.inf)
        if source >= m:
            return dist
        edges = [(a, b, w) for a, b, w in self.shortcuts if a < m and b < m]
        ea = np.array([e[0] for e in edges], dtype=np.int64)
        eb = np.array([e[1] for e in edges], dtype=np.int64)
        ew = np.array([e[2] for e in edges], dtype=np.float64)
        d = relax(self.arc, source, ea, eb, ew)     # compiled (``loop_kernel``)
        k = min(n, m)
        dist[:k] = d[:k]
        return dist


class LoopCloser:
    # class defaults, so that a closer pickled before they were added has them too
    field_bytes = FIELD_CACHE_BYTES   # the fields' bound (``slam-log`` lowers it)
    single_submaps = False            # submaps' points in single precision (``slam-log``)

    def __init__(self, cfg: LoopClosureConfig, icp_params: IcpParams) -> None:
        self.cfg = cfg
        self.icp_params = icp_params
        self.submaps: list[Submap] = []
        self.stats = LoopStats()
        self._graph = _Graph()
        self._owner = new_owner()            # its fields in the process's cache
        self._pending: list[LoopClosure] = []

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state.pop("_owner", None)            # fields are a cache of what the submaps give again
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        state.pop("_fields", None)           # a snapshot of an older release kept them here
        self.__dict__.update(state)
        self._owner = new_owner()            # a copy does not share the original's fields

    # -- bookkeeping ---------------------------------------------------------------------
    def add_edge(self, i: int, j: int, length_m: float) -> None:
        """Chain edges (k−1, k) in order, or loop edges between any two keyframes."""
        self._graph.add_edge(i, j, length_m)

    def maybe_close_submap(self, keyframes: list[Keyframe], poses: F64) -> None:
        """Freeze the next block of keyframes into a submap once it is complete."""
        b = self.cfg.block_keyframes
        while len(keyframes) >= (len(self.submaps) + 1) * b:
            self._close_block(len(self.submaps) * b, keyframes, poses)

    def _close_block(self, start: int, keyframes: list[Keyframe], poses: F64) -> None:
        b = self.cfg.block_keyframes
        members = list(range(start, start + b))
        anchor = start + b // 2
        pts, nrm = points_in_frame([keyframes[i] for i in members], poses[members],
                                   poses[anchor], voxel_m=0.5 * self.cfg.resolution_m,
                                   max_range_m=self.cfg.submap_range_m)
        if len(pts) < 20:
            pts = np.zeros((1, 2)) if len(pts) == 0 else pts
            nrm = np.zeros((len(pts), 2)) if len(nrm) == 0 else nrm
        kind = np.float32 if self.single_submaps else np.float64
        pts, nrm = np.array(pts, dtype=kind), np.array(nrm, dtype=kind)
        pts.flags.writeable = nrm.flags.writeable = False
        self.submaps.append(Submap(anchor, members, pts, nrm))

    def _field(self, sm_index: int) -> LikelihoodField:
        f = FIELDS.get(self._owner, sm_index)
        if f is None:
            sm = self.submaps[sm_index]
            res = self.cfg.resolution_m
            f = LikelihoodField(np.asarray(sm.points, dtype=np.float64), res, sigma_m=res,
                                margin_m=4 * res, levels=7)
            FIELDS.put(self._owner, sm_index, f, self.field_bytes, FIELD_CACHE)
        return f

    # -- search --------------------------------------------------------------------------
    def candidates(self, k: int, poses: F64, narrow: bool = False
                   ) -> list[tuple[int, float, float]]:
        """Submaps to try for keyframe k: (submap index, window [m], window [rad]); the window
        no larger than ``narrow_radius_max_m`` and ``narrow_angle_max_deg`` for a narrow
        sensor's keyframe."""
        c = self.cfg
        r_max, a_max = ((min(c.radius_max_m, c.narrow_radius_max_m),
                         min(c.angle_max_deg, c.narrow_angle_max_deg)) if narrow
                        else (c.radius_max_m, c.angle_max_deg))
        if not self.submaps:
            return []
        dist = self._graph.distances_from(k, len(poses))
        near = np.hypot(poses[:, 0] - poses[k, 0], poses[:, 1] - poses[k, 1])
        out: list[tuple[float, int, float, float]] = []
        for si, sm in enumerate(self.submaps):
            d_graph = float(dist[sm.anchor])
            if k in sm.members or d_graph < c.min_graph_distance_m:
                continue
            if not math.isfinite(d_graph):  # not connected: nothing bounds the drift
                d_graph = 1e9
            radius = min(r_max, c.radius_base_m + c.radius_per_m * d_graph)
            angle = min(a_max, c.angle_base_deg + c.angle_per_m_deg * d_graph)
            gap = float(np.min(near[sm.members]))
            if gap <= radius + 1.0:
                out.append((gap - radius, si, radius, math.radians(angle)))
        out.sort()
        return [(si, r, a) for _, si, r, a in out[: c.max_candidates]]

    def search(self, k: int, keyframes: list[Keyframe], poses: F64, narrow: bool = False
               ) -> list[LoopClosure]:
        """Verified closures for keyframe k (confirmed ones only; others may stay pending).
        ``narrow``: the keyframes are a narrow sensor's (see ``candidates``)."""
        c = self.cfg
        self.stats.searches += 1
        cands = self.candidates(k, poses, narrow)
        if not cands:
            return []
        q0 = max(0, k - c.query_keyframes + 1)
        query_kfs = keyframes[q0:k + 1]
        q_pts, q_nrm = points_in_frame(query_kfs, poses[q0:k + 1], poses[k],
                                       voxel_m=c.resolution_m, max_range_m=c.submap_range_m)
        if len(q_pts) < 30:
            return []
        found: list[LoopClosure] = []
        for si, radius, angle in cands:
            self.stats.candidates += 1
            sm = self.submaps[si]
            T_center = between(poses[sm.anchor], poses[k])
            lc = self._verify(si, k, q_pts, q_nrm, T_center, radius, angle)
            if lc is not None:
                found.append(lc)
        return self._confirm(found, poses)

    def _verify(self, si: int, k: int, q_pts: F64, q_nrm: F64, T_center: F64, radius: float,
                angle: float) -> LoopClosure | None:
        c = self.cfg
        sm = self.submaps[si]
        (coarse_pts,) = voxel_thin(q_pts, c.search_voxel_m)
        coarse = search(self._field(si), coarse_pts, T_center, radius, angle, c.min_score,
                        c.ambiguity_ratio)
        if coarse is None:
            self.stats.rejected_score += 1
            return None
        if coarse.second_score > 0.0:  # another pose in the window fits almost as well
            self.stats.rejected_ambiguous += 1
            return None
        res: MatchResult = icp(q_pts, q_nrm, PointMap(sm.points, sm.normals), coarse.T_map_scan,
                               self.icp_params)
        if res.inlier_fraction < c.min_inlier_fraction or not math.isfinite(res.rms_m):
            self.stats.rejected_icp += 1
            return None
        if res.degenerate:
            self.stats.rejected_degenerate += 1
            return None
        corr_m, _ = pose_distance(between(T_center, res.T_map_scan))
        return LoopClosure(sm.anchor, k, res.T_map_scan, res.information, coarse.score, corr_m)

    def _confirm(self, found: list[LoopClosure], poses: F64) -> list[LoopClosure]:
        """Small corrections pass; large ones need another closure consistent with them."""
        c = self.cfg
        out: list[LoopClosure] = []
        for lc in found:
            if lc.correction_m <= c.confirm_correction_m:
                out.append(lc)
                continue
            if lc.score < c.confirm_min_score:
                self.stats.rejected_weak += 1
                continue
            partner = next((p for p in self._pending if self._consistent(p, lc, poses)), None)
            if partner is None:
                self._pending.append(lc)
                self.stats.pending += 1
                continue
            self._pending.remove(partner)
            out.extend([partner, lc])
        # pending closures expire when the robot has moved on without confirmation
        if found:
            newest = max(lc.keyframe for lc in found)
            stale = [p for p in self._pending if newest - p.keyframe > c.pending_keyframes]
            for p in stale:
                self._pending.remove(p)
                self.stats.rejected_unconfirmed += 1
        self.stats.accepted += len(out)
        return out

    def _consistent(self, a: LoopClosure, b: LoopClosure, poses: F64) -> bool:
        """Does the cycle anchor_a → kf_a → kf_b → anchor_b → anchor_a close?"""
        if abs(a.keyframe - b.keyframe) < self.cfg.query_keyframes:
            return False  # the two queries would share keyframes: not independent evidence
        T_ka_kb = between(poses[a.keyframe], poses[b.keyframe])
        T_aa_ab = between(poses[a.anchor], poses[b.anchor])
        cycle = compose(compose(a.T_anchor_kf, T_ka_kb), inverse(b.T_anchor_kf))
        err = between(T_aa_ab, cycle)
        d, ang = pose_distance(err)
        return d <= self.cfg.confirm_tolerance_m and ang <= math.radians(
            self.cfg.confirm_tolerance_deg)
