"""Teams: robots whose graphs are joined by verified rendezvous, and the evidence for a merge.

A tag sighting of robot B by robot A, placed on both robots' keyframes, gives by the direct
method an estimate of the transform from B's team frame to A's team frame. ``MergeVerifier``
collects these estimates per pair of teams and proposes a merge only when enough of them agree
(χ² gate on their covariances), and the caller's map check (the two grids aligned by the fused
transform contradict each other in few cells) does not object. ``join_graph`` then builds the
joint GTSAM problem: every member's factors (one prior: the anchor's), the rendezvous factors,
initial values in the anchor's frame; a batch optimisation first, then ISAM2 carries on.
No I/O here.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.rendezvous import (
    Sighting,
    between,
    compose,
    direct_transform,
    fuse_transforms,
    inverse,
    transform_covariance,
)
from server.slam import RobotSlam
from server.slam.backend import FactorRecord, PoseGraph
from server.slam.grid import OccupancyGrid

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: χ² (3 dof) at 99 %: two estimates of one transform farther apart are not the same
CHI2_3DOF_99 = 11.34


@dataclass(frozen=True)
class SightingRecord:
    """One sighting placed in the graph: observer ``a`` saw ``b`` at ``stamp_ns``."""

    stamp_ns: int
    observer: str
    observed: str
    sighting: Sighting
    kf_a: int
    T_kf_a: F64           # the observer relative to its keyframe kf_a at the sighting
    kf_b: int
    T_kf_b: F64
    T_ab: F64             # direct method: b's team frame -> a's team frame
    cov_ab: F64           # its covariance, (x, y, θ)
    p_seen_a: F64         # the observed robot's position by the sighting, in a's team frame
    p_own_b: F64          # the observed robot's position by its own SLAM, in b's team frame
    sigma_p_m: float      # σ of p_seen_a (range, bearing and pose uncertainty, isotropic)
    flipped: bool = False  # T_ab/cov_ab were inverted (the verifier's pair order)


@dataclass(frozen=True)
class MergeProposal:
    team_a: str
    team_b: str
    records: tuple[SightingRecord, ...]
    T_ab: F64             # fused: team b's frame -> team a's frame
    cov_ab: F64
    direct_first: F64     # the direct method on the first sighting alone


def make_record(stamp_ns: int, observer: str, observed: str, sighting: Sighting,
                at_a: tuple[int, F64], at_b: tuple[int, F64], P_a: F64, P_b: F64,
                pose_sigmas: Sequence[float]) -> SightingRecord:
    """``P_a``/``P_b``: the robots' poses at the sighting in their own team frames."""
    T_ab = direct_transform(P_a, sighting, P_b)
    cov = transform_covariance(P_a, sighting, P_b, pose_sigmas)
    seen = compose(P_a, sighting.relative_pose())[:2]
    r = sighting.range_m
    sig = math.sqrt(sighting.sigma_range_m ** 2 + (r * sighting.sigma_bearing_rad) ** 2
                    + 2 * pose_sigmas[0] ** 2 + (r * pose_sigmas[2]) ** 2)
    return SightingRecord(stamp_ns, observer, observed, sighting, at_a[0], at_a[1],
                          at_b[0], at_b[1], T_ab, cov, seen, np.asarray(P_b[:2], float), sig)


def chi2_between(T1: F64, C1: F64, T2: F64, C2: F64) -> float:
    d = np.asarray(T1, dtype=np.float64) - np.asarray(T2, dtype=np.float64)
    d[2] = math.remainder(d[2], 2 * math.pi)
    return float(d @ np.linalg.solve(C1 + C2, d))


@dataclass
class VerifierParams:
    min_sightings: int = 3          # consistent sightings needed (2 when both saw each other)
    window_s: float = 60.0          # sightings older than this (scan time) are forgotten
    gate_sigmas: float = 3.0        # a sighting agrees with a transform within this many σ
    gate_floor_m: float = 0.05
    # a tag's yaw this good fixes the rotation by itself. Views from one spot share their
    # error (a robot that stopped 1.2 m from another reads its tag's yaw ~2° off, frame after
    # frame), so only a very close view counts; otherwise two places (or both robots seeing
    # each other, which puts both robots' positions in the fit) fix it
    informative_yaw_rad: float = math.radians(2.5)
    min_baseline_m: float = 1.0     # two sightings this far apart fix the rotation
    # ... well enough only when the fitted rotation is this certain: a degree off at the
    # meeting point is 0.3 m off 17 m away, where the robots started
    max_rotation_sigma_rad: float = math.radians(1.0)
    max_pair_hypotheses: int = 300


@dataclass
class PairEvidence:
    records: list[SightingRecord] = field(default_factory=list)
    rejected_by_map: int = 0


class MergeVerifier:
    """Sightings between teams, per unordered pair of teams; proposes merges."""

    def __init__(self, params: VerifierParams | None = None) -> None:
        self.p = params or VerifierParams()
        self.pairs: dict[tuple[str, str], PairEvidence] = {}

    @staticmethod
    def _key(a: str, b: str) -> tuple[str, str]:
        return (a, b) if a <= b else (b, a)

    def add(self, team_a: str, team_b: str, rec: SightingRecord) -> MergeProposal | None:
        """Record a sighting from team a's robot of team b's; a proposal when the evidence
        of this pair agrees (transforms expressed as team_lo -> ... see ``MergeProposal``)."""
        key = self._key(team_a, team_b)
        if key != (team_a, team_b):  # store every transform as key[1] -> key[0]
            rec = _flip(rec)
        ev = self.pairs.setdefault(key, PairEvidence())
        ev.records.append(rec)
        horizon = rec.stamp_ns - int(self.p.window_s * 1e9)
        ev.records = [r for r in ev.records if r.stamp_ns >= horizon]
        return self._propose(key, ev)

    def _propose(self, key: tuple[str, str], ev: PairEvidence) -> MergeProposal | None:
        """RANSAC over the pair's sightings. Each one ties the observed robot's position in
        both team frames (range and bearing are accurate; a tag's yaw often is not past a few
        metres), and, when its yaw is informative, gives the whole transform by itself.
        Hypotheses: single informative sightings and pairs of sightings far enough apart;
        the largest consistent set wins and is refined by weighted least squares."""
        recs = ev.records
        if len(recs) < 2:
            return None
        p = self.p
        xX = np.array([_in_x(r) for r in recs])
        xY = np.array([_in_y(r) for r in recs])
        sig = np.array([r.sigma_p_m for r in recs])
        informative = np.array([r.sighting.sigma_yaw_rad <= p.informative_yaw_rad for r in recs])
        hyps: list[F64] = [r.T_ab for r, ok in zip(recs, informative, strict=True) if ok]
        n = len(recs)
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)
                 if np.hypot(*(xY[i] - xY[j])) >= p.min_baseline_m]
        step = max(1, len(pairs) // p.max_pair_hypotheses)
        for i, j in pairs[::step]:
            hyps.append(rigid_fit(xY[[i, j]], xX[[i, j]], 1.0 / sig[[i, j]] ** 2))
        best: NDArray[np.bool_] | None = None
        best_cost = math.inf
        for T in hyps:
            inl = self._inliers(T, recs, xX, xY, sig, informative)
            cost = float(np.sum(_residuals(T, xX, xY)[inl] / sig[inl]))
            if best is None or inl.sum() > best.sum() or (inl.sum() == best.sum()
                                                          and cost < best_cost):
                best, best_cost = inl, cost
        if best is None:
            return None
        members = [r for r, ok in zip(recs, best, strict=True) if ok]
        idx = np.flatnonzero(best)
        mutual = len({r.observer for r in members}) > 1
        need = max(2, p.min_sightings - (1 if mutual else 0))
        if not informative[idx].any():
            need += 1  # two sightings define a position-only hypothesis: two more confirm it
        if len(members) < need:
            return None
        spread = float(np.max(np.hypot(*(xY[idx] - xY[idx].mean(axis=0)).T)))
        has_yaw = bool(informative[idx].any())
        if spread < p.min_baseline_m / 2 and not has_yaw:
            return None  # the rotation is not observable yet
        w = 1.0 / sig[idx] ** 2
        s_t = math.sqrt(1.0 / w.sum())
        if spread >= p.min_baseline_m / 2:
            T = rigid_fit(xY[idx], xX[idx], w)
            s_r = s_t / spread
        else:
            yaw = [r for r, ok in zip(members, informative[idx], strict=True) if ok]
            Ty, Cy = fuse_transforms([r.T_ab for r in yaw], [r.cov_ab for r in yaw])
            T = rigid_fit(xY[idx], xX[idx], w, theta=float(Ty[2]))
            s_r = math.sqrt(max(float(Cy[2, 2]), 0.0))
        if s_r > p.max_rotation_sigma_rad:
            return None  # agreeing, but the rotation is not pinned down yet
        C = np.diag([s_t ** 2, s_t ** 2, s_r ** 2])
        first = min(members, key=lambda r: r.stamp_ns)
        return MergeProposal(key[0], key[1], tuple(members), T, C, first.T_ab.copy())

    def _inliers(self, T: F64, recs: list[SightingRecord], xX: F64, xY: F64, sig: F64,
                 informative: NDArray[np.bool_]) -> NDArray[np.bool_]:
        ok = _residuals(T, xX, xY) <= self.p.gate_sigmas * sig + self.p.gate_floor_m
        for i, r in enumerate(recs):
            if ok[i] and informative[i]:
                d = abs(math.remainder(r.T_ab[2] - T[2], 2 * math.pi))
                ok[i] = d <= self.p.gate_sigmas * math.sqrt(r.cov_ab[2, 2]) + math.radians(2)
        return ok

    def reject(self, proposal: MergeProposal) -> None:
        """The map check objected: forget these sightings."""
        ev = self.pairs.get((proposal.team_a, proposal.team_b))
        if ev is None:
            return
        ids = {id(r) for r in proposal.records}
        ev.records = [r for r in ev.records if id(r) not in ids]
        ev.rejected_by_map += 1

    def forget(self, team: str) -> None:
        """A team no longer exists (merged into another): its pending evidence goes."""
        self.pairs = {k: v for k, v in self.pairs.items() if team not in k}

    def rejected_total(self) -> int:
        return sum(v.rejected_by_map for v in self.pairs.values())


def _in_x(r: SightingRecord) -> F64:
    """The observed robot's position in the pair's first team's frame."""
    return r.p_own_b if r.flipped else r.p_seen_a


def _in_y(r: SightingRecord) -> F64:
    """... and in the second team's frame."""
    return r.p_seen_a if r.flipped else r.p_own_b


def _flip(rec: SightingRecord) -> SightingRecord:
    """The same sighting with the transform the other way round (a's frame -> b's frame)."""
    T = inverse(rec.T_ab)
    c, s = math.cos(rec.T_ab[2]), math.sin(rec.T_ab[2])
    # covariance of the inverse, to first order: -Ad(T) in tangent space; in (x, y, θ)
    # coordinates the translation part rotates by -θ and picks up the lever arm
    x, y = rec.T_ab[0], rec.T_ab[1]
    J = np.array([[-c, -s, s * x - c * y], [s, -c, c * x + s * y], [0.0, 0.0, -1.0]])
    cov = J @ rec.cov_ab @ J.T
    return SightingRecord(rec.stamp_ns, rec.observer, rec.observed, rec.sighting, rec.kf_a,
                          rec.T_kf_a, rec.kf_b, rec.T_kf_b, T, 0.5 * (cov + cov.T),
                          rec.p_seen_a, rec.p_own_b, rec.sigma_p_m, not rec.flipped)


def _residuals(T: F64, xX: F64, xY: F64) -> F64:
    c, s = math.cos(T[2]), math.sin(T[2])
    moved = xY @ np.array([[c, s], [-s, c]]) + T[:2]
    return np.asarray(np.hypot(*(xX - moved).T), dtype=np.float64)


def rigid_fit(src: F64, dst: F64, weights: F64, theta: float | None = None) -> F64:
    """Weighted least-squares 2D rigid transform (x, y, θ) mapping ``src`` onto ``dst``
    (N, 2); with ``theta`` given only the translation is fitted."""
    w = np.asarray(weights, dtype=np.float64) / np.sum(weights)
    ms, md = w @ src, w @ dst
    a, b = src - ms, dst - md
    if theta is None:
        sxx = float(np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])))
        sxy = float(np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])))
        theta = math.atan2(sxy, sxx)
    c, s = math.cos(theta), math.sin(theta)
    t = md - np.array([c * ms[0] - s * ms[1], s * ms[0] + c * ms[1]])
    return np.array([t[0], t[1], math.remainder(theta, 2 * math.pi)])


# -- map agreement -------------------------------------------------------------------------
@dataclass(frozen=True)
class MapAgreement:
    overlap_cells: int        # cells known in both grids
    occupied_checked: int     # occupied cells (either grid) inside the overlap
    conflicts: int            # occupied in one where the other is clearly free

    @property
    def conflict_ratio(self) -> float:
        return self.conflicts / self.occupied_checked if self.occupied_checked else 0.0


def map_agreement(grid_a: OccupancyGrid, grid_b: OccupancyGrid, T_ab: F64,
                  tolerance_cells: int = 2) -> MapAgreement:
    """How grid b, moved into a's frame by ``T_ab``, agrees with grid a: an occupied cell of
    either conflicts when the other grid says free there, with no occupied cell within
    ``tolerance_cells`` (walls are a cell or two thick and alignments are not perfect) and
    only free cells one more cell around. A wall that beams grazed is partly erased in a map
    (they cross its cells on their way to hits farther along it), but such free cells still
    border the unknown behind the wall; a wall put into the middle of a room by a wrong
    transform has free space all around."""
    from scipy.ndimage import maximum_filter, minimum_filter

    occ_a, free_a = grid_a.occupied_mask(), grid_a.free_mask()
    occ_b, free_b = grid_b.occupied_mask(), grid_b.free_mask()
    if not occ_a.size or not occ_b.size:
        return MapAgreement(0, 0, 0)
    size = 2 * tolerance_cells + 1
    near_a = maximum_filter(occ_a, size=size)
    near_b = maximum_filter(occ_b, size=size)
    open_a = minimum_filter(free_a, size=size + 2)
    open_b = minimum_filter(free_b, size=size + 2)
    rb, cb = np.nonzero(occ_b | free_b)
    res_b = grid_b.resolution_m
    pts_b = np.stack([grid_b.origin[0] + (cb + 0.5) * res_b,
                      grid_b.origin[1] + (rb + 0.5) * res_b], axis=1)
    c, s = math.cos(T_ab[2]), math.sin(T_ab[2])
    pa = pts_b @ np.array([[c, s], [-s, c]]) + T_ab[:2]
    ij = grid_a.cell_of(pa)
    h, w = occ_a.shape
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    ia, ja = ij[inside, 1], ij[inside, 0]
    rb, cb = rb[inside], cb[inside]
    known_a = occ_a[ia, ja] | free_a[ia, ja]
    ia, ja, rb, cb = ia[known_a], ja[known_a], rb[known_a], cb[known_a]
    b_occ, b_free = occ_b[rb, cb], free_b[rb, cb]
    a_occ, a_free = occ_a[ia, ja], free_a[ia, ja]
    conflicts = int((b_occ & a_free & ~near_a[ia, ja] & open_a[ia, ja]).sum()
                    + (a_occ & b_free & ~near_b[rb, cb] & open_b[rb, cb]).sum())
    checked = int((b_occ | a_occ).sum())
    return MapAgreement(len(ia), checked, conflicts)


# -- the joint problem ---------------------------------------------------------------------
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


# -- refining a merge on the maps ------------------------------------------------------------
@dataclass(frozen=True)
class CrossMatch:
    """Keyframe kb of robot b matched against robot a's keyframes around it."""

    ka: int
    kb: int
    T_ka_kb: F64
    information: F64      # in kb's frame (the between factor's error space)
    inlier_fraction: float
    turn_rad: float = 0.0  # how far the match turned kb from where it was placed


def cross_matches(a: RobotSlam, b: RobotSlam, every: int = 4, radius_m: float = 5.0,
                  min_inlier_fraction: float = 0.5, max_correction_m: float = 0.5,
                  max_correction_rad: float = math.radians(5.0),
                  T_ab: F64 | None = None, tried: list[int] | None = None,
                  only: list[int] | None = None) -> list[CrossMatch]:
    """Scan-to-map matches of b's keyframes (every ``every``-th, or those in ``only``) against
    a's keyframes within ``radius_m``, both placed by the current joint estimate (or b's by
    ``T_ab``): the overlap of the two maps says how they fit together, far more precisely than
    tag sightings.
    Matches that moved the keyframe implausibly far, matched poorly or were degenerate are left
    out; ``tried[0]`` is increased for every keyframe that had a map to match against."""
    from server.slam.frontend import icp_params
    from server.slam.icp import icp
    from server.slam.keyframes import local_point_map

    if not a.keyframes or not b.keyframes:
        return []
    pa, pb = a.keyframe_poses(), b.keyframe_poses()
    if T_ab is not None:  # b's keyframes not yet in a's frame: place them by T_ab
        pb = np.array([compose(T_ab, P) for P in pb])
    params = icp_params(a.cfg.matcher)
    out: list[CrossMatch] = []
    last = len(b.keyframes) - 1
    picked = (sorted({*range(0, last, max(1, every)), last}) if only is None  # newest: the meeting
              else sorted(k for k in set(only) if 0 <= k <= last))
    for kb in picked:
        d = np.hypot(pa[:, 0] - pb[kb, 0], pa[:, 1] - pb[kb, 1])
        near = np.flatnonzero(d <= radius_m)
        scan = b.keyframes[kb].matchable
        if len(near) == 0 or len(scan) < a.cfg.matcher.min_points:
            continue
        target = local_point_map([a.keyframes[i] for i in near], pa[near],
                                 a.cfg.local_map.voxel_m)
        if len(target) < a.cfg.matcher.min_points:
            continue
        if tried is not None:
            tried[0] += 1
        m = icp(scan.points, scan.normals, target, pb[kb], params)
        shift = math.hypot(*(m.T_map_scan[:2] - pb[kb, :2]))
        turn = abs(math.remainder(m.T_map_scan[2] - pb[kb, 2], 2 * math.pi))
        if (not m.converged or m.degenerate or m.inlier_fraction < min_inlier_fraction
                or shift > max_correction_m or turn > max_correction_rad):
            continue
        ka = int(near[np.argmin(d[near])])
        c, s = math.cos(m.T_map_scan[2]), math.sin(m.T_map_scan[2])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.append(CrossMatch(ka, kb, between(pa[ka], m.T_map_scan),
                              R.T @ m.information @ R, m.inlier_fraction,
                              math.remainder(m.T_map_scan[2] - pb[kb, 2], 2 * math.pi)))
    return out
