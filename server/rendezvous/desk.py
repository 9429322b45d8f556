"""The sightings desk: every tag sighting the robots report comes here first.

1. Intake: a robot's own tag and sightings beyond the usable range are counted and dropped; a
   sighting of another team's robot is passed on as a call to both robots' lookouts.
2. Waiting: a sighting waits until both robots' scans around its time are in (or it expires).
3. Placing: it is placed on both robots' keyframes (``make_record``); a sighting that puts a
   robot where the observer's teammate stands is a misread tag and goes no further.
4. Between teams it goes to the merger as evidence; within a team it is checked against the
   team's graph: agreeing, it may become a factor; contradicting, it is kept, and enough
   contradictions that agree among themselves ask the merger to undo the merge.
No I/O here.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from factors.noise import NoiseError
from factors.rendezvous import Sighting
from schemas import TagDetection, TagDetections
from schemas.se2 import compose, inverse, transform_points
from server.config import ServerConfig
from server.fleet.model import Fleet, RobotContext, Sighted
from server.rendezvous.counters import RendezvousCounters
from server.rendezvous.evidence import (
    CHI2_3DOF_99,
    SightingRecord,
    agrees_with_team,
    chi2_between,
    make_record,
    seen_sigma_m,
)
from server.rendezvous.merger import Merger

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


class SightingDesk:
    """Intake, pending queue and time matching of tag sightings (one thread)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, merger: Merger,
                 counters: RendezvousCounters, pose_sigmas: tuple[float, float, float]) -> None:
        self.cfg, self.fleet, self.merger, self.counters = cfg, fleet, merger, counters
        self.pose_sigmas = pose_sigmas
        self.pending: list[tuple[int, str, TagDetection]] = []
        #: sightings between teammates that disagree with their team's graph, per pair
        self.contradictions: dict[tuple[str, str], list[SightingRecord]] = {}

    # -- 1. intake -------------------------------------------------------------------------
    def receive(self, msg: TagDetections) -> None:
        """Queue a robot's tag sightings until the scans around their time are in."""
        if not self.cfg.teams.enabled:
            return
        for det in msg.detections:
            self.counters.sightings += 1
            if det.observed_robot_id == msg.robot_id:
                self.counters.own_tag += 1
                continue
            self._call(msg.robot_id, det, msg.stamp_ns)
            if det.range_m > self._usable_range_m(det):
                self.counters.too_far += 1
                continue
            self.pending.append((msg.stamp_ns, msg.robot_id, det))
        latest = max((r.last_stamp_ns for r in self.fleet.robots.values()), default=0)
        self.process(max(latest, msg.stamp_ns))

    def _usable_range_m(self, det: TagDetection) -> float:
        """How far a sighting may be to count: a tag's own range and centre are good only
        close up, the LIDAR's off the robot's body much farther."""
        t = self.cfg.teams
        if det.located_by == "lidar":
            return max(t.max_sighting_range_m, t.max_lidar_sighting_range_m)
        return t.max_sighting_range_m

    def _call(self, observer: str, det: TagDetection, stamp_ns: int | None = None) -> None:
        """A robot of another team was seen: tell both robots where the other one is, so they
        close in until the tags can be read well (see server.lookout). Not when the tag was
        seen where a teammate of the observer stands: that is the teammate's tag, misread
        (placing it later says the same, but by then both robots would have turned to it)."""
        t = self.cfg.teams
        robots = self.fleet.robots
        a, b = robots.get(observer), robots.get(det.observed_robot_id)
        if a is None or b is None or a.team_id == b.team_id or not t.look_at_movers or \
                t.approach_range_m <= 0 or not a.scans or not b.scans:
            return
        if not all(math.isfinite(v) for v in (det.range_m, det.bearing_rad, det.yaw_rad)):
            return   # counted as bad where the sighting itself is refused
        if a.meeting is None and b.meeting is None and self.fleet.seeking_paused(
                a.team_id, b.team_id, max(a.last_stamp_ns, b.last_stamp_ns)):
            self.counters.calls_paused += 1
            return   # their maps keep refusing the merge: both go on exploring
        rel = np.array([det.range_m * math.cos(det.bearing_rad),
                        det.range_m * math.sin(det.bearing_rad), det.yaw_rad])
        seen = transform_points(a.pose, rel[None, :2])[0]
        mate = self._teammate_near(a, b.robot_id, det, seen,
                                   a.last_stamp_ns if stamp_ns is None else stamp_ns)
        if mate is not None:
            self.counters.calls_misread += 1
            log.debug("no call from %s's sighting of %s: %s stands there", a.robot_id,
                      b.robot_id, mate)
            return
        now_a, now_b = a.last_stamp_ns * 1e-9, b.last_stamp_ns * 1e-9
        a.look.hear(now_a, seen,
                    max(0.5, 0.1 * det.range_m), sure=True, caller=b.robot_id)
        # the reader as the seen robot would place it: through the tag's heading, which is
        # poor at range, hence the wide tolerance
        back = inverse(rel)
        b.look.hear(now_b, transform_points(b.pose, back[None, :2])[0],
                    max(1.0, 0.35 * det.range_m), sure=False, range_m=det.range_m,
                    range_tolerance_m=3.0 * det.sigma_range_m + 0.2, caller=a.robot_id)

    def _teammate_near(self, a: RobotContext, observed: str, det: TagDetection, seen: F64,
                       stamp_ns: int) -> str | None:
        """A teammate of observer ``a`` (not the robot named) whose latest pose is where the
        tag was seen (``seen``, by ``a``'s latest pose): within the gate a placed sighting
        gets (``_teammate_there``), widened by how far either robot can have driven between
        the sighting and its latest pose."""
        vp = self.merger.verifier.p
        sig = seen_sigma_m(det.range_m, det.sigma_range_m, det.sigma_bearing_rad,
                           self.pose_sigmas)
        gate = vp.gate_sigmas * sig + vp.gate_floor_m
        v = self.cfg.control.v_mps
        for cid in self.fleet.team_of(a).robot_ids:
            if cid in (a.robot_id, observed):
                continue
            c = self.fleet.robots[cid]
            if not c.scans:
                continue
            lag_s = (abs(a.last_stamp_ns - stamp_ns) + abs(c.last_stamp_ns - stamp_ns)) * 1e-9
            if float(np.hypot(*(c.pose[:2] - seen))) <= gate + min(v * lag_s, 1.0):
                return cid
        return None

    # -- 2. waiting for the scans around a sighting's time ---------------------------------
    def process(self, now_ns: int) -> None:
        """Place the sightings whose scans are in; drop those that expired."""
        t = self.cfg.teams
        keep = []
        for stamp, observer, det in self.pending:
            a = self.fleet.robots.get(observer)
            b = self.fleet.robots.get(det.observed_robot_id)
            if a is None or b is None:
                if now_ns - stamp > t.max_pending_s * 1e9:
                    self.counters.unknown_robot += 1
                    log.info("sighting of unknown robot %s by %s dropped",
                             det.observed_robot_id, observer)
                else:
                    keep.append((stamp, observer, det))
                continue
            tol = int(t.sighting_tolerance_s * 1e9)
            at_a, at_b = a.slam.pose_at(stamp, tol), b.slam.pose_at(stamp, tol)
            if at_a is None or at_b is None:
                if min(a.last_stamp_ns, b.last_stamp_ns) > stamp + tol or \
                        now_ns - stamp > t.max_pending_s * 1e9:
                    self.counters.expired += 1
                else:
                    keep.append((stamp, observer, det))
                continue
            try:
                self._place(stamp, a, b, det, at_a, at_b)
            except NoiseError as e:
                self.counters.bad += 1
                log.warning("sighting by %s refused: %s", observer, e)
        self.pending = keep

    # -- 3. placing it on the keyframes ----------------------------------------------------
    def _place(self, stamp: int, a: RobotContext, b: RobotContext, det: TagDetection,
               at_a: tuple[int, F64], at_b: tuple[int, F64]) -> None:
        s = Sighting(det.range_m, det.bearing_rad, det.yaw_rad, det.sigma_range_m,
                     det.sigma_bearing_rad, det.sigma_yaw_rad)
        P_a = compose(a.slam.keyframe_pose(at_a[0]), at_a[1])
        P_b = compose(b.slam.keyframe_pose(at_b[0]), at_b[1])
        rec = make_record(stamp, a.robot_id, b.robot_id, s, at_a, at_b, P_a, P_b,
                          self.pose_sigmas)
        self.counters.used += 1
        same_team = a.team_id == b.team_id
        if not (same_team and self._agrees(rec)):
            mate = self._teammate_there(a, rec)
            if mate is not None:
                # two robots are never in one place: the tag is the teammate's, misread
                self.counters.misread += 1
                log.info("sighting of %s by %s at %s's place: taken for a misread tag",
                         b.robot_id, a.robot_id, mate)
                return
        # -- 4. to the merger, or checked against the team
        if not same_team:
            self._note_frames(a, b, rec)
            self.merger.consider(a.team_id, b.team_id, rec)
        elif det.range_m > self.cfg.teams.max_sighting_range_m:
            # from afar (located by the LIDAR) a sighting helps find a team; within one,
            # the maps matched against each other say more
            self.counters.within_team += 1
        else:
            self._within_team(rec)

    @staticmethod
    def _note_frames(a: RobotContext, b: RobotContext, rec: SightingRecord) -> None:
        """Each robot of the pair learns where the other's team frame lies in its own, by this
        sighting, so that it keeps clear of the other robot for a while wherever that robot's
        own pose puts it (``Fleet.others_in_robot_frame``): a camera turned away on its tower
        does not see the robot beside it."""
        T_ab = inverse(rec.T_ab) if rec.flipped else rec.T_ab
        a.sighted = {**(a.sighted or {}),
                     b.robot_id: Sighted(a.last_stamp_ns, T_ab.copy(), a.team_id, b.team_id)}
        b.sighted = {**(b.sighted or {}),
                     a.robot_id: Sighted(b.last_stamp_ns, inverse(T_ab), b.team_id, a.team_id)}

    def _agrees(self, rec: SightingRecord) -> bool:
        return agrees_with_team(rec, self.merger.verifier.p)

    def _teammate_there(self, a: RobotContext, rec: SightingRecord) -> str | None:
        """A teammate of the observer (other than the robot named) that its team's graph puts
        where the sighting saw the tag, at the sighting's time: a misread tag id reads as a
        robot standing exactly where a teammate is."""
        vp = self.merger.verifier.p
        gate = vp.gate_sigmas * rec.sigma_p_m + vp.gate_floor_m
        tol = int(self.cfg.teams.sighting_tolerance_s * 1e9)
        for cid in self.fleet.team_of(a).robot_ids:
            if cid in (rec.observer, rec.observed):
                continue
            c = self.fleet.robots[cid]
            at = c.slam.pose_at(rec.stamp_ns, tol)
            if at is None:
                continue
            p = compose(c.slam.keyframe_pose(at[0]), at[1])[:2]
            if float(np.hypot(*(p - rec.p_seen_a))) <= gate:
                return cid
        return None

    # -- 4b. within a team -----------------------------------------------------------------
    def _within_team(self, rec: SightingRecord) -> None:
        """A sighting between teammates: another factor if it agrees with the team's graph;
        consistent disagreement undoes the merge that joined them."""
        t = self.cfg.teams
        self.counters.within_team += 1
        team = self.fleet.team_of(self.fleet.robots[rec.observer])
        pair = (min(rec.observer, rec.observed), max(rec.observer, rec.observed))
        if self._agrees(rec):
            self.contradictions.pop(pair, None)
            self.merger.add_team_sighting(team, rec)
            return
        self.counters.contradicting += 1
        bad = self.contradictions.setdefault(pair, [])
        bad.append(rec)
        bad[:] = [r for r in bad if r.stamp_ns >= rec.stamp_ns - t.window_s * 1e9]
        agreeing = [r for r in bad
                    if chi2_between(r.T_ab, r.cov_ab, rec.T_ab, rec.cov_ab) <= CHI2_3DOF_99]
        if len(agreeing) >= t.undo_after:
            self.contradictions.pop(pair, None)
            self.merger.undo(team, rec.stamp_ns, pair)
