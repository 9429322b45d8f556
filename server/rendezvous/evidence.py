"""Evidence for a merge: tag sightings placed on keyframes, and the verifier that weighs them.

A tag sighting of robot B by robot A, placed on both robots' keyframes, gives by the direct
method an estimate of the transform from B's team frame to A's team frame (``make_record``).
``MergeVerifier`` collects these estimates per pair of teams and proposes a merge only when
enough of them agree (RANSAC over the pair's sightings, χ² gate on their covariances); the
merger then checks the proposal on the maps. ``agrees_with_team`` judges a sighting between
robots already in one team against the team's graph. No I/O here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from factors.rendezvous import (
    Sighting,
    direct_transform,
    fuse_transforms,
    transform_covariance,
)
from schemas.se2 import compose, inverse, wrap_angle

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


def seen_sigma_m(range_m: float, sigma_range_m: float, sigma_bearing_rad: float,
                 pose_sigmas: Sequence[float]) -> float:
    """σ of where a sighting places the robot it saw (isotropic): the sighting's range and
    bearing, and both robots' own pose uncertainty."""
    return math.sqrt(sigma_range_m ** 2 + (range_m * sigma_bearing_rad) ** 2
                     + 2 * pose_sigmas[0] ** 2 + (range_m * pose_sigmas[2]) ** 2)


def make_record(stamp_ns: int, observer: str, observed: str, sighting: Sighting,
                at_a: tuple[int, F64], at_b: tuple[int, F64], P_a: F64, P_b: F64,
                pose_sigmas: Sequence[float]) -> SightingRecord:
    """``P_a``/``P_b``: the robots' poses at the sighting in their own team frames."""
    T_ab = direct_transform(P_a, sighting, P_b)
    cov = transform_covariance(P_a, sighting, P_b, pose_sigmas)
    seen = compose(P_a, sighting.relative_pose())[:2]
    sig = seen_sigma_m(sighting.range_m, sighting.sigma_range_m, sighting.sigma_bearing_rad,
                       pose_sigmas)
    return SightingRecord(stamp_ns, observer, observed, sighting, at_a[0], at_a[1],
                          at_b[0], at_b[1], T_ab, cov, seen, np.asarray(P_b[:2], float), sig)


def chi2_between(T1: F64, C1: F64, T2: F64, C2: F64) -> float:
    d = np.asarray(T1, dtype=np.float64) - np.asarray(T2, dtype=np.float64)
    d[2] = wrap_angle(d[2])
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
    # sightings from one place (``one_place``) whose tags' yaws give the turn to this [rad]
    # (σ) pick the one turn of a square building's walls that fits (a quarter turn apart)
    max_rough_turn_rad: float = math.radians(12.0)
    # sightings of a robot that moved a little (``short_path``): pairs this far apart make
    # hypotheses, and the turn their places fit must be good to this [rad] (σ) to pick the
    # quarter turn of the square walls: 3σ stays well short of the 45° to the next one
    min_path_baseline_m: float = 0.1
    max_path_turn_rad: float = math.radians(8.0)


@dataclass(frozen=True)
class OnePlace:
    """Sightings of one robot standing in one place (``MergeVerifier.one_place``): its
    position in both teams' frames, and the turn between them only as roughly as the tags'
    yaws give it."""

    team_a: str
    team_b: str
    records: tuple[SightingRecord, ...]
    x_a: F64              # the seen robot's positions in team a's frame (N, 2)
    x_b: F64              # ... in team b's
    weights: F64
    rough_turn_rad: float
    rough_sigma_rad: float

    def proposal(self, turn_rad: float, sigma_rad: float) -> MergeProposal:
        """The merge these sightings make with the turn known otherwise."""
        T = rigid_fit(self.x_b, self.x_a, self.weights, theta=turn_rad)
        s_t = math.sqrt(1.0 / float(self.weights.sum()))
        first = min(self.records, key=lambda r: r.stamp_ns)
        return MergeProposal(self.team_a, self.team_b, self.records, T,
                             np.diag([s_t ** 2, s_t ** 2, sigma_rad ** 2]), first.T_ab.copy())


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

    def _arrays(self, recs: list[SightingRecord]) -> tuple[
            np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The seen robot's positions in the pair's first and second team frames (``_in_x``,
        ``_in_y``), their σ, and which sightings have an informative yaw."""
        xX = np.array([_in_x(r) for r in recs])
        xY = np.array([_in_y(r) for r in recs])
        sig = np.array([r.sigma_p_m for r in recs])
        informative = np.array([r.sighting.sigma_yaw_rad <= self.p.informative_yaw_rad
                                for r in recs])
        return xX, xY, sig, informative

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
        xX, xY, sig, informative = self._arrays(recs)
        best = self._consensus(recs, xX, xY, sig, informative, p.min_baseline_m)
        if best is None:
            return None
        members = [r for r, ok in zip(recs, best, strict=True) if ok]
        idx = np.flatnonzero(best)
        if len(members) < self._needed(members, informative[idx]):
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

    def _consensus(self, recs: list[SightingRecord], xX: F64, xY: F64, sig: F64,
                   informative: NDArray[np.bool_], baseline_m: float
                   ) -> NDArray[np.bool_] | None:
        """RANSAC: the largest set of sightings that agree with one transform. Hypotheses:
        single informative sightings and pairs at least ``baseline_m`` apart."""
        p = self.p
        hyps: list[F64] = [r.T_ab for r, ok in zip(recs, informative, strict=True) if ok]
        n = len(recs)
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)
                 if np.hypot(*(xY[i] - xY[j])) >= baseline_m]
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
        return best

    def _needed(self, members: list[SightingRecord], informative: NDArray[np.bool_]) -> int:
        """Sightings a consistent set needs to be proposed."""
        mutual = len({r.observer for r in members}) > 1
        need = max(2, self.p.min_sightings - (1 if mutual else 0))
        if not informative.any():
            need += 1  # two sightings define a position-only hypothesis: two more confirm it
        return need

    def short_path(self, team_a: str, team_b: str) -> OnePlace | None:
        """The largest set of the pair's sightings that agree, when the places they put the
        seen robot at lie too close together to fix the turn to ``max_rotation_sigma_rad``
        (``_propose`` then waits for the robot to drive on), with the turn they give roughly:
        the least-squares fit's, its σ from the places' spread about their weighted mean
        (1/√Σ wᵢ·dᵢ²). None when they are too few or the turn is not good to
        ``max_path_turn_rad``."""
        key = self._key(team_a, team_b)
        ev = self.pairs.get(key)
        p = self.p
        if ev is None or len(ev.records) < p.min_sightings + 1:
            return None
        recs = ev.records
        xX, xY, sig, informative = self._arrays(recs)
        best = self._consensus(recs, xX, xY, sig, informative, p.min_path_baseline_m)
        if best is None:
            return None
        idx = np.flatnonzero(best)
        members = [recs[i] for i in idx]
        if len(members) < max(p.min_sightings + 1, self._needed(members, informative[idx])):
            return None
        w = 1.0 / sig[idx] ** 2
        lever = xY[idx] - (w @ xY[idx]) / w.sum()
        info = float(np.sum(w * np.sum(lever ** 2, axis=1)))
        if info <= 0.0:
            return None
        sigma = 1.0 / math.sqrt(info)
        if sigma > p.max_path_turn_rad:
            return None
        T = rigid_fit(xY[idx], xX[idx], w)
        return OnePlace(key[0], key[1], tuple(members), xX[idx], xY[idx], w, float(T[2]),
                        sigma)

    def one_place(self, team_a: str, team_b: str) -> OnePlace | None:
        """The largest set of the pair's sightings that agree on where the seen robot stood,
        whatever the turn between the two frames, when they cannot fix that turn (one place,
        no tag yaw good enough: ``_propose`` then waits); with the turn their tags' yaws give,
        roughly. None when the agreeing sightings are too few or the rough turn is not even
        good to ``max_rough_turn_rad``."""
        key = self._key(team_a, team_b)
        ev = self.pairs.get(key)
        if ev is None or len(ev.records) < self.p.min_sightings + 1:
            return None
        recs = ev.records
        xX = np.array([_in_x(r) for r in recs])
        xY = np.array([_in_y(r) for r in recs])
        sig = np.array([r.sigma_p_m for r in recs])
        gate = self.p.gate_sigmas * sig + self.p.gate_floor_m
        best: NDArray[np.bool_] | None = None
        for i in range(len(recs)):   # a place in both frames at once: the turn plays no part
            inl = (np.hypot(*(xX - xX[i]).T) <= gate + gate[i]) & \
                (np.hypot(*(xY - xY[i]).T) <= gate + gate[i])
            if best is None or inl.sum() > best.sum():
                best = inl
        assert best is not None
        members = [r for r, ok in zip(recs, best, strict=True) if ok]
        if len(members) < self.p.min_sightings + 1:
            return None
        yaws = np.array([r.T_ab[2] for r in members])
        turn = float(np.angle(np.mean(np.exp(1j * yaws))))
        spread = float(np.median(np.abs(np.angle(np.exp(1j * (yaws - turn))))))
        sigma = max(spread, float(np.median([math.sqrt(r.cov_ab[2, 2]) for r in members])))
        if sigma > self.p.max_rough_turn_rad:
            return None
        idx = np.flatnonzero(best)
        return OnePlace(key[0], key[1], tuple(members), xX[idx], xY[idx],
                        1.0 / sig[idx] ** 2, turn, sigma)

    def _inliers(self, T: F64, recs: list[SightingRecord], xX: F64, xY: F64, sig: F64,
                 informative: NDArray[np.bool_]) -> NDArray[np.bool_]:
        ok = _residuals(T, xX, xY) <= self.p.gate_sigmas * sig + self.p.gate_floor_m
        for i, r in enumerate(recs):
            if ok[i] and informative[i]:
                d = abs(wrap_angle(r.T_ab[2] - T[2]))
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
    return np.array([t[0], t[1], wrap_angle(theta)])


def agrees_with_team(rec: SightingRecord, p: VerifierParams) -> bool:
    """Whether a sighting between teammates agrees with where the team's graph has them: the
    seen robot's position within the gate, and, where the tag's yaw is informative, the
    heading too (``T_ab`` is then about the identity)."""
    miss = float(np.hypot(*(rec.p_seen_a - rec.p_own_b)))
    agrees = miss <= p.gate_sigmas * rec.sigma_p_m + p.gate_floor_m
    if agrees and rec.sighting.sigma_yaw_rad <= p.informative_yaw_rad:
        agrees = abs(wrap_angle(rec.T_ab[2])) <= \
            p.gate_sigmas * math.sqrt(rec.cov_ab[2, 2]) + math.radians(2)
    return agrees
