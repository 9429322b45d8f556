"""One robot's turns toward what moves, and its approaches (see ``server.lookout``)."""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import transform_points, wrap_angle
from server.control import Twist
from server.lookout.movers import LookParams, bearing_to, moving_objects, objects_at_range
from server.lookout.offers import Offers
from server.planning import OccupancyGrid

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)


class Lookout:
    """One robot's turns toward moving things (see the module docstring)."""

    #: how far its range sensor sees [m] (its latest scan's maximum range, set by steering;
    #: 0 while not known)
    sensor_range_m: float = 0.0
    #: rough calls dropped: its sensor would have seen the reader at the reader's distance,
    #: and nothing stood there (a tag misread, or read where no robot was)
    calls_unseen: int = 0

    def __init__(self, params: LookParams | None = None, name: str = "") -> None:
        self.p = params or LookParams()
        self.name = name                     # the robot's id, for log lines
        self.heading: float | None = None    # where to look, map frame
        self.started_s = 0.0
        self.hold_until_s: float | None = None
        self.meeting = False                 # facing a robot known to be close
        self.next_s = -math.inf
        self.meet_next_s = -math.inf
        self.looks = 0
        self.approaches = 0
        #: the thing followed (map frame), when it was last seen, in how many scans in a row
        self.track: F64 | None = None
        self.track_seen_s = 0.0
        self.track_count = 0
        self.approaching = False
        self.heading_error = 0.0             # of the last command (for obstacle avoidance)
        self.moved = False                   # an approach drove the robot somewhere
        #: a tag sighting's word on where another team's robot is: (map xy, tolerance, sure, s)
        self.call: tuple[F64, float, bool, float] | None = None
        #: ... and, when the reader's distance is known, that distance and its tolerance
        self.call_range: tuple[float, float] | None = None
        self.spin_until_s: float | None = None   # turning on the spot to find a reader
        self.spin_sign = 1.0                      # ... which way (toward the call first)
        self.calls = 0
        self.caller = ""                     # the robot of the latest call
        #: the detours it starts, to be priced before they go on (``server.lookout.offers``)
        self.offers = Offers()

    @property
    def active(self) -> bool:
        return self.heading is not None or self.approaching or self.spin_until_s is not None

    def hear(self, now_s: float, xy: F64, tolerance_m: float, sure: bool,
             range_m: float | None = None, range_tolerance_m: float = 0.3,
             caller: str = "") -> None:
        """A tag sighting places another team's robot at ``xy`` (map frame) within
        ``tolerance_m``; ``sure``: the place is good enough to drive to without the LIDAR's
        confirmation. ``range_m``: how far away it is, known better than where (a robot seen
        by another learns the distance between them from the reader, the direction only
        through the tag's heading). Taken up at the next scan (see the module docstring).
        ``caller``: that robot; its calls are not heard while a detour about it is declined."""
        xy = np.asarray(xy, dtype=np.float64)
        if self.offers.refused(caller, now_s):
            return
        if self.approaching and self.track is not None and \
                math.hypot(*(xy - self.track)) <= max(tolerance_m, self.p.track_m):
            self.track_seen_s = now_s    # the followed thing is the robot that was seen
            if sure:
                self.track = xy
            return
        self.call, self.caller = (xy, tolerance_m, sure, now_s), caller
        self.call_range = None if range_m is None else (float(range_m), float(range_tolerance_m))

    def _near_call(self, pose: F64) -> bool:
        """A call from within tag range, not already faced, not right after a meeting. The
        other robot is reading this one's tag now: facing it may be all a merge still needs,
        so the cooldown of other looks does not hold it back."""
        if self.call is None or self.call[3] < self.meet_next_s:
            return False
        return self._close(self.call[0], pose) and not (self.heading is not None and self.meeting)

    def _close(self, xy: F64, pose: F64) -> bool:
        """Within (about) tag-reading range of the robot."""
        return math.hypot(*(xy - pose[:2])) <= self.p.max_range_m + 0.5

    def _answer_now(self, now_s: float, pose: F64, points_robot: F64,
                    grid: OccupancyGrid | None, mates_xy: F64, range_m: float) -> Twist | None:
        """Drop whatever the robot was doing and take up the call."""
        self.reset()
        groups = [] if grid is None else moving_objects(points_robot, pose, grid, mates_xy,
                                                        self.p, range_m)
        return self._answer(now_s, pose, groups, points_robot, grid)

    def _answer(self, now_s: float, pose: F64, groups: list[tuple[F64, int]],
                points_robot: F64 | None = None, grid: OccupancyGrid | None = None
                ) -> Twist | None:
        """Take up the latest call; None when it leads nowhere."""
        assert self.call is not None
        xy, tol, sure, t = self.call
        ranged, self.call, self.call_range = self.call_range, None, None
        if now_s - t > self.p.lost_s:
            return None
        # close by, even a rough place is worth driving to: tags are read only within
        # max_range_m, and the other robot is looking for this one too
        near = self._close(xy, pose)
        if not sure and ranged is not None and points_robot is not None:
            # something standing free at the reader's distance is the reader, whatever the
            # tag's heading said about the direction: face it (the reader is coming)
            there = objects_at_range(points_robot, pose, grid, *ranged)
            if there:
                reader = min(there, key=lambda c: math.hypot(*(c - xy)))
                self.calls += 1
                log.info("%s: answering a call from %.1f m away (rough): facing what stands "
                         "at that distance", self.name, ranged[0])
                self.offers.make("call", self.caller, reader, now_s)
                self._look_toward(now_s, pose, reader, meet=True)
                return self.step(now_s, pose, np.zeros((0, 2)), None, np.zeros((0, 2)))
            if grid is not None and sum(ranged) < self.sensor_range_m and \
                    ranged[0] > self.p.max_range_m + 0.5:
                # the scan reaches past the reader's distance all round, and nothing stands
                # there: no robot read this one's tag from there. Turning on the spot for it
                # (below) would cost a whole turn for a tag misread or read where no robot
                # stood: in case 4, such calls came 0-10 times a run with false tag views,
                # at most once without (a sensor that sees less far still turns). A reader
                # within tag range is still faced: one standing that close for a while is
                # in the map's walls, not free (a depth robot at 1.4 m, in one run)
                self.calls_unseen += 1
                log.info("%s: a call from %.1f m away not answered: nothing stands at that "
                         "distance", self.name, ranged[0])
                return None
        best = min(groups, key=lambda g: math.hypot(*(g[0] - xy)), default=None)
        target = best[0] if best is not None and math.hypot(*(best[0] - xy)) <= tol else \
            (xy if sure or near else None)
        self.calls += 1
        log.info("%s: answering a call from %.1f m away (%s): %s", self.name,
                 math.hypot(*(xy - pose[:2])), "sure" if sure else "rough",
                 "look" if target is None else "go and look")
        self.offers.make("call", self.caller, xy if target is None else target, now_s)
        if target is None:
            # the place is rough, but its side is not: turning toward it first finds the
            # reader in a fraction of the turn (a camera robot turned 250° the other way,
            # 3 s, in one run)
            self.spin_sign = 1.0 if bearing_to(pose, xy) >= 0.0 else -1.0
            self.spin_until_s = now_s + 2 * math.pi / self.p.omega_rps
            return Twist(0.0, self.spin_sign * self.p.omega_rps)
        if math.hypot(*(target - pose[:2])) <= self.p.approach_stop_m + 0.3:
            self._look_toward(now_s, pose, target, meet=True)
            return self.step(now_s, pose, np.zeros((0, 2)), None, np.zeros((0, 2)))
        self.track, self.track_seen_s = target, now_s
        return self._start_approach(now_s, pose, groups)

    def decline(self, now_s: float, until_s: float) -> None:
        """The detour just offered is not worth its time: drop it, and hear no calls about
        its robot (or seek nothing, for a seek) until ``until_s``."""
        offer = self.offers.pending
        self.reset()
        self.call, self.call_range = None, None
        if offer is None:
            return
        self.offers.decline(offer, until_s)
        if offer.kind == "seek":
            self.next_s = max(self.next_s, until_s)

    def forget(self) -> None:
        """Drop what the robot was looking at and any call: the map frame changed under them
        (a merge), and the robot that called may now be a teammate."""
        self.reset()
        self.call, self.call_range = None, None

    def reset(self) -> None:
        self.heading, self.hold_until_s, self.spin_until_s = None, None, None
        self.meeting = False
        self.approaching, self.track, self.track_count = False, None, 0

    def step(self, now_s: float, pose: F64, points_robot: F64, grid: OccupancyGrid | None,
             mates_xy: F64) -> Twist | None:
        """A command while looking, else None (the navigator drives)."""
        p = self.p
        if self._near_call(pose):
            return self._answer_now(now_s, pose, points_robot, grid, mates_xy,
                                    p.max_range_m + 1.0)
        if self.spin_until_s is not None:
            if self.call is not None and self.call[2]:    # it read the reader's tag
                return self._answer_now(now_s, pose, points_robot, grid, mates_xy,
                                        max(p.max_range_m, p.approach_range_m))
            if now_s < self.spin_until_s:
                return Twist(0.0, self.spin_sign * p.omega_rps)
            self.reset()
            self.next_s = now_s + p.cooldown_s
            return None
        if self.heading is None:
            if now_s < self.next_s or grid is None:
                return None
            groups = moving_objects(points_robot, pose, grid, mates_xy, p,
                                    max(p.max_range_m, p.approach_range_m))
            if self.approaching:
                return self._approach(now_s, pose, groups, points_robot)
            if self.call is not None and p.approach_range_m > 0:
                return self._answer(now_s, pose, groups, points_robot, grid)
            near = next((c for c, n in groups if n >= p.min_points
                         and math.hypot(*(c - pose[:2])) <= p.max_range_m), None)
            if near is None:
                self._follow(now_s, pose, groups)
                if self.track_count < p.approach_confirm:
                    return None
                self.offers.make("seek", "", np.asarray(self.track), now_s)
                return self._start_approach(now_s, pose, groups)
            if p.approach_range_m > p.max_range_m and \
                    math.hypot(*(near - pose[:2])) > p.approach_stop_m + p.track_m:
                # in reading range, but only close up does a tag give the other's heading
                self.track, self.track_seen_s = near, now_s
                self.offers.make("seek", "", near, now_s)
                return self._start_approach(now_s, pose, groups)
            bearing = bearing_to(pose, near)
            if abs(bearing) <= p.half_fov_rad:
                return None
            self.offers.make("seek", "", near, now_s)
            self._look_toward(now_s, pose, near)
        if self.meeting and self.call is not None and self.call[2] and \
                p.approach_range_m > 0 and not self._close(self.call[0], pose):
            # facing a reader found by its distance, its tag is now read too: go closer,
            # where both tags and the maps' overlap say more
            return self._answer_now(now_s, pose, points_robot, grid, mates_xy,
                                    max(p.max_range_m, p.approach_range_m))
        err = wrap_angle(self.heading - pose[2])
        self.heading_error = err
        if self.hold_until_s is None:
            if abs(err) > p.aligned_rad and now_s - self.started_s < p.max_turn_s:
                return Twist(0.0, math.copysign(p.omega_rps, err))
            self.hold_until_s = now_s + (p.meet_hold_s if self.meeting else p.hold_s)
        if now_s < self.hold_until_s:
            return Twist(0.0, 0.0)
        if self.meeting:
            self.meet_next_s = now_s + p.meet_cooldown_s
        self.reset()
        self.next_s = now_s + p.cooldown_s
        return None

    def _start_approach(self, now_s: float, pose: F64, groups: list[tuple[F64, int]]
                        ) -> Twist | None:
        self.approaching, self.started_s = True, now_s
        self.approaches += 1
        log.info("%s: approaching something that moves at %s (%.1f m away)", self.name,
                 np.asarray(self.track).round(2), math.hypot(*(np.asarray(self.track) - pose[:2])))
        return self._approach(now_s, pose, groups, np.zeros((0, 2)))

    def _look_toward(self, now_s: float, pose: F64, xy: F64, meet: bool = False) -> None:
        self.heading = wrap_angle(pose[2] + bearing_to(pose, xy))
        self.meeting = meet
        self.started_s, self.hold_until_s = now_s, None
        self.approaching = False
        self.looks += 1

    def _nearest_to_track(self, groups: list[tuple[F64, int]]) -> F64 | None:
        track = self.track
        if track is None:
            return None
        best = min(groups, key=lambda g: math.hypot(*(g[0] - track)), default=None)
        if best is None or math.hypot(*(best[0] - track)) > self.p.track_m:
            return None
        return best[0]

    def _follow(self, now_s: float, pose: F64, groups: list[tuple[F64, int]]) -> None:
        """Count the scans in a row a far group was seen near one place."""
        p = self.p
        far = [(c, n) for c, n in groups if n >= p.approach_min_points
               and p.max_range_m < math.hypot(*(c - pose[:2])) <= p.approach_range_m]
        if p.approach_range_m <= p.max_range_m or not far:
            self.track, self.track_count = None, 0
            return
        seen = self._nearest_to_track(far)
        if seen is None:
            self.track, self.track_count = far[0][0], 1
        else:
            self.track, self.track_count = seen, self.track_count + 1
        self.track_seen_s = now_s

    def _approach(self, now_s: float, pose: F64, groups: list[tuple[F64, int]],
                  points_robot: F64) -> Twist | None:
        """Drive toward the followed group; look at it once close. Once followed, the thing
        is tracked on the raw returns too: a robot that stands still for a while is mapped
        as an obstacle, and would no longer count as something in free space."""
        p = self.p
        seen = self._nearest_to_track(groups)
        if seen is None and self.track is not None and len(points_robot):
            world = transform_points(pose, np.asarray(points_robot).reshape(-1, 2))
            d = np.hypot(*(world - self.track).T)
            if d.min() <= p.track_m:
                nearest = world[int(np.argmin(d))]
                seen = world[np.hypot(*(world - nearest).T) <= p.cluster_m].mean(axis=0)
        if seen is not None:
            self.track, self.track_seen_s = seen, now_s
        if self.track is None or now_s - self.track_seen_s > p.lost_s or \
                now_s - self.started_s > p.approach_max_s:
            log.info("%s: approach given up after %.1f s: %s", self.name, now_s - self.started_s,
                     "too long" if now_s - self.started_s > p.approach_max_s else "lost")
            self.reset()
            self.next_s = now_s + p.cooldown_s
            return None
        dist = math.hypot(*(self.track - pose[:2]))
        if dist <= p.approach_stop_m:
            self._look_toward(now_s, pose, self.track, meet=True)
            return self.step(now_s, pose, np.zeros((0, 2)), None, np.zeros((0, 2)))
        err = bearing_to(pose, self.track)
        self.heading_error = err
        v = p.approach_v_mps if abs(err) < math.radians(35.0) else 0.0
        self.moved = self.moved or v > 0
        return Twist(v, float(np.clip(2.0 * err, -p.omega_rps, p.omega_rps)))


class NullLookout(Lookout):
    """The lookout of a server that does not look at movers: it hears no calls and never
    turns or drives."""

    def hear(self, now_s: float, xy: F64, tolerance_m: float, sure: bool,
             range_m: float | None = None, range_tolerance_m: float = 0.3,
             caller: str = "") -> None:
        return None

    def step(self, now_s: float, pose: F64, points_robot: F64, grid: OccupancyGrid | None,
             mates_xy: F64) -> Twist | None:
        return None
