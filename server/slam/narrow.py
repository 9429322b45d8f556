"""A narrow sensor's scans: a depth camera, turned on a tower or fixed (``docs/mixed-sensors.md``).

A scan that spans a few tens of degrees and a few metres often shows one wall, which pins the
pose only across it. ``NarrowSensor`` is the pipeline's ``SensorModel`` for such scans:

1. **Prepare**: normals from more beams (``scan.narrow_normal_window``): the camera's beams
   lie closer together and its depth is noisier.
2. **Match**: stricter pairing of normals (``matcher.narrow_min_normal_cos``) and a prior on
   the odometry from a smaller base (``narrow_prior_sigma_*``).
3. **Place**: the pose averaged over the latest matches (``server.slam.smoothing``), the
   odometry's while the robot stands still for a whole scan; or, when
   the views the camera took while the robot stood still make a whole 360° scan
   (``server.slam.sweep``), that scan, matched against the whole scans before it, and it
   becomes a keyframe.
4. **Keyframe**: also when much of the scan is new to the local map (``keyframes.novel_*``).
5. **Factors**: a whole scan's match, from the whole scan before it (kind ``"sweep"``); square
   walls' heading ties (``server.slam.heading_ties``).
6. **Local map**: more keyframes (``local_map.narrow_keyframes``) and the teammates' walls
   around the robot (``local_map.guide_radius_m``).
7. **Stand still** while the turning camera makes a whole scan (``Sweep.due``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, pose_distance, transform_points
from server.slam.backend import add_constraint
from server.slam.config import SlamConfig
from server.slam.frontend import (
    FrontendMatch,
    MatchKind,
    icp_params,
    match_scan,
    match_step,
    odometry_prior,
)
from server.slam.heading_ties import HeadingTies
from server.slam.icp import PointMap, translation_degeneracy
from server.slam.keyframes import Keyframe, gather, local_point_map, voxel_mean
from server.slam.loop_closure import edge_length_m
from server.slam.measurements import match_factor
from server.slam.scan import ScanPoints
from server.slam.sensor import LidarSensor, SensorChoice, scan_points
from server.slam.smoothing import RecentMatches
from server.slam.sweep import Sweep
from server.slam.view import Placement, SlamView

F64 = NDArray[np.float64]
IDENTITY = np.zeros(3)
#: a point of the robot's own map this close to a teammate's is left to the teammate's: where
#: a wide sensor mapped the place, its map is the reference, and the narrow robot's own walls
#: there, drawn from drifting poses, would only pull it off (a drift under this much)
GUIDE_OVERLAP_M = 0.5
#: whole scans before the new one that it is matched against
WHOLES_MATCHED = 3
#: a whole scan matched against a wide teammate's map may move the pose this far from the
#: prediction (the drift it corrects) [m], and turn it this much [deg]; a match further off
#: is a wall taken for another
GUIDED_MAX_SHIFT_M = 0.25
GUIDED_MAX_TURN_DEG = 3.0
#: ... and must pair this share of its points with the map's
GUIDED_MIN_INLIERS = 0.7
#: where its information along one direction is under this share of the other's (the
#: translation's, ``translation_degeneracy``) and gives that direction a σ over
#: ``GUIDED_WEAK_SIGMA_M``, the match keeps the prediction along that direction: a whole
#: scan 3 m deep that sees one wall's length and little across it slid the robot 0.19 m
#: along the wall at a ratio of 0.022 and 1.4 cm (the matcher's own limit is
#: ``matcher.degenerate_eigen_ratio``, 0.02); a scan whose weak direction is held by a
#: pillar or a door frame, to millimetres, keeps its match
GUIDED_WEAK_RATIO = 0.1
GUIDED_WEAK_SIGMA_M = 0.01
MATCHED = (MatchKind.ICP, MatchKind.DEGENERATE)
#: the pose averaged over the latest matches may lie this far [m] and turn this much [deg]
#: from the newest match: the average takes out a narrow match's noise (centimetres, a
#: degree). Further off, the matches kept no longer agree with where the robot is: the
#: average moved a robot 1 m along a wall in one step while its match and its odometry
#: agreed within 3 cm; they are dropped, and the newest match stands
SMOOTHED_MAX_SHIFT_M = 0.1
SMOOTHED_MAX_TURN_DEG = 3.0


class NarrowSensor:
    """A depth camera's narrow views, its whole scans and its square walls (see the module)."""

    narrow = True

    def __init__(self, cfg: SlamConfig, ties: HeadingTies) -> None:
        self.cfg = cfg
        self.icp_wide = icp_params(cfg.matcher)     # whole scans are 360° ones
        self.icp = dataclasses.replace(self.icp_wide,
                                       min_normal_cos=cfg.matcher.narrow_min_normal_cos)
        self.local_keyframes = cfg.local_map.narrow_keyframes
        self.recent = RecentMatches(cfg.matcher.narrow_smoothing)
        self.sweep = Sweep(cfg.sweep)
        self.ties = ties
        self.wholes: list[int] = []      # keyframes of the whole scans

    # -- 1, 2: prepare and match ---------------------------------------------------------
    def prepare(self, ranges_m: F64, angles_rad: F64, free_m: float) -> ScanPoints:
        return scan_points(ranges_m, angles_rad, self.cfg.scan,
                           self.cfg.scan.narrow_normal_window, free_m)

    def match(self, scan: ScanPoints, local_map: PointMap, T_pred: F64, T_last: F64,
              T_step_velocity: F64, T_step_odom: F64) -> FrontendMatch:
        return match_step(scan, local_map, T_pred, T_last, T_step_velocity, T_step_odom,
                          self.cfg.matcher, self.icp, narrow=True)

    # -- 3: place ------------------------------------------------------------------------
    def place(self, slam: SlamView, scan: ScanPoints, match: FrontendMatch, T_odom_robot: F64,
              T_pred: F64, T_last: F64, T_step_odom: F64) -> Placement:
        """The narrow scan at its smoothed pose; or the whole scan it completes, at the pose
        of its own match where that was found (else of the narrow scan's)."""
        whole = self.sweep.add(scan, T_odom_robot) if self.sweep.cfg.enabled else None
        if whole is None and len(self.sweep.views) >= 2:
            # standing still for a whole scan: the odometry has not moved, and a view of one
            # side, matched, can only slide the pose along what it sees (10 cm in 2 s in one
            # run); the whole scan at the end of the turn places it
            return Placement(scan, FrontendMatch(T_pred, MatchKind.ODOMETRY, np.zeros((3, 3)), 0.0))
        if whole is None or len(whole) < self.cfg.matcher.min_points:
            return Placement(scan, self._smoothed(slam, match, T_odom_robot))
        found = self._match_whole(slam, whole, T_odom_robot, T_pred, T_last, T_step_odom)
        if found is None:   # it sees mostly what the map has not: still the better keyframe
            return Placement(whole, self._smoothed(slam, match, T_odom_robot), whole=True)
        m, matched_to = found
        slam.stats.sweeps += 1
        self.recent.clear()       # the whole scan outweighs the views before it
        return Placement(whole, self._smoothed(slam, m, T_odom_robot), whole=True,
                         matched_to=matched_to)

    def _match_whole(self, slam: SlamView, whole: ScanPoints, T_odom_robot: F64, T_pred: F64,
                     T_last: F64, T_step_odom: F64) -> tuple[FrontendMatch, int | None] | None:
        """The whole scan's match and the keyframe of the whole scan it was matched against
        (None: against the local map); None when it did not match. Against the whole scans
        before it where there are some: taken standing still, what they drew is not smeared
        by the narrow views' drift. A match there that moves the pose from the odometry's
        by more than ``sweep.max_shift_m`` or ``max_turn_deg`` is a wall taken for another,
        and the local map, drawn by the narrow views, would not say better."""
        mc, sw = self.cfg.matcher, self.sweep.cfg
        guided = self._match_guided(slam, whole, T_pred, T_last)
        if guided is not None:
            return guided, None
        if self.wholes:
            prev = self.wholes[-1]
            kfs = [slam.keyframes[i] for i in self.wholes[-WHOLES_MATCHED:]]
            poses = slam.graph.poses([slam.trajectory.key(kf.index) for kf in kfs])
            target = local_point_map(kfs, poses, self.cfg.local_map.voxel_m)
            if len(target) >= mc.min_points:
                from_prev = between(slam.keyframes[prev].T_odom_robot, T_odom_robot)
                T_guess = compose(poses[-1], from_prev)
                m = match_scan(whole, target, T_guess, T_guess, IDENTITY, False, mc,
                               self.icp_wide, self._prior(from_prev))
                d, a = pose_distance(between(T_guess, m.T_map_robot))
                near = d <= sw.max_shift_m and a <= math.radians(sw.max_turn_deg)
                if m.kind in MATCHED and near:
                    slam.stats.sweep_shift_m = d
                    return m, prev
                return None
        assert slam.local_map is not None
        m = match_scan(whole, slam.local_map, T_pred, T_last, slam.velocity, False, mc,
                       self.icp_wide, self._prior(T_step_odom))
        if m.kind not in MATCHED:
            return None
        slam.stats.sweep_shift_m = pose_distance(between(T_pred, m.T_map_robot))[0]
        return m, None

    def _match_guided(self, slam: SlamView, whole: ScanPoints, T_pred: F64, T_last: F64
                      ) -> FrontendMatch | None:
        """The whole scan matched against the local map where a wide teammate drew the place
        around the robot (its keyframes within ``local_map.guide_radius_m``: the local map
        holds the teammate's walls there, the robot's own only elsewhere), the team's
        reference: the robot's own whole scans before it carry its drift, the teammate's do not.
        None without such a map, or when the match is not a full one (a corridor's walls
        leave the pose free along it) or moves the pose further than ``GUIDED_MAX_*``."""
        lm, mc = self.cfg.local_map, self.cfg.matcher
        if not slam.guides or lm.guide_radius_m <= 0:
            return None
        guide = _guide_points(slam, T_pred, lm.guide_radius_m)
        if guide is None or len(guide[0]) < mc.min_points:
            return None
        assert slam.local_map is not None   # the teammate's walls, its own elsewhere
        m = match_scan(whole, slam.local_map, T_pred, T_last, IDENTITY, False, mc,
                       self.icp_wide, None)
        if m.kind != MatchKind.ICP or m.inlier_fraction < GUIDED_MIN_INLIERS:
            return None
        weak = translation_degeneracy(m.information, GUIDED_WEAK_RATIO)
        if weak is not None and _information_along(m.information, weak) < \
                GUIDED_WEAK_SIGMA_M ** -2:
            # it says where the robot is across its walls, not along them
            T = m.T_map_robot.copy()
            T[:2] += weak * float(weak @ (T_pred[:2] - T[:2]))
            m = dataclasses.replace(m, T_map_robot=T)
        d, a = pose_distance(between(T_pred, m.T_map_robot))
        if d > GUIDED_MAX_SHIFT_M or a > math.radians(GUIDED_MAX_TURN_DEG):
            return None
        slam.stats.sweep_shift_m = d
        slam.stats.guided_sweeps += 1
        return m

    def _prior(self, T_step_odom: F64) -> F64 | None:
        mc = self.cfg.matcher
        return odometry_prior(T_step_odom, mc) if mc.use_odometry_prior else None

    def _smoothed(self, slam: SlamView, match: FrontendMatch, T_odom_robot: F64
                  ) -> FrontendMatch:
        """The match averaged with the latest ones; the match alone (and the others dropped)
        where the average lands further from it than ``SMOOTHED_MAX_*``."""
        key = slam.trajectory.key(slam.anchor.index)
        sm = self.recent.smoothed(match, T_odom_robot, key, slam.anchor.T_map_kf,
                                  slam.graph.pose, self.cfg.graph)
        d, a = pose_distance(between(match.T_map_robot, sm.T_map_robot))
        if d <= SMOOTHED_MAX_SHIFT_M and a <= math.radians(SMOOTHED_MAX_TURN_DEG):
            return sm
        self.recent.clear()
        slam.stats.smoothing_resets += 1
        return self.recent.smoothed(match, T_odom_robot, key, slam.anchor.T_map_kf,
                                    slam.graph.pose, self.cfg.graph)

    # -- 4, 5: keyframes -----------------------------------------------------------------
    def sees_new(self, scan: ScanPoints, T_map_robot: F64, local_map: PointMap) -> bool:
        k = self.cfg.keyframes
        d_near, _ = local_map.tree.query(transform_points(T_map_robot, scan.points),
                                         distance_upper_bound=k.novel_m)
        return float(np.mean(~np.isfinite(d_near))) >= k.novel_fraction

    def on_keyframe(self, slam: SlamView, k: int, placed: Placement, T_odom_robot: F64
                    ) -> None:
        """A whole scan's match against the one before, as a factor from it (the anchor's
        factor carried the odometry only); the first whole scan, taken where the robot
        started, as the square walls' reference; the square walls' ties."""
        g, tr = slam.graph, slam.trajectory
        T_map_robot = placed.match.T_map_robot
        if placed.matched_to is not None:
            w = placed.matched_to
            T_w = between(g.pose(tr.key(w)), T_map_robot)
            add_constraint(g, tr, match_factor(tr.key(w), tr.key(k), T_w, placed.match,
                                               self.cfg.graph), "sweep")
            slam.loops.add_edge(w, k, edge_length_m(T_w))
        if placed.whole:
            self.wholes.append(k)
            if self.ties.reference is None:
                sw = self.sweep.cfg
                self.ties.set_reference(placed.scan.normals, slam.keyframes[0].T_odom_robot,
                                        T_odom_robot, sw.still_m, sw.still_deg)
        if self.ties.tie(g, tr, k, placed.scan.normals, T_map_robot):
            slam.stats.heading_ties += 1

    # -- 6, 7: local map, standing still -------------------------------------------------
    def local_map(self, slam: SlamView, keyframes: Sequence[Keyframe], T_map_kf: F64
                  ) -> PointMap:
        """The keyframes' points; with teammates in the graph (``slam.guides``), their walls
        around the robot where they have them, in place of its own within
        ``GUIDE_OVERLAP_M``: a narrow sensor matches against the map its team's wide sensors
        drew where they drew it, its own drifting keyframes only elsewhere."""
        lm = self.cfg.local_map
        guide = (_guide_points(slam, T_map_kf[-1], lm.guide_radius_m)
                 if slam.guides and lm.guide_radius_m > 0 else None)
        if guide is None:
            return local_point_map(keyframes, T_map_kf, lm.voxel_m)
        pts, nrm = gather(keyframes, T_map_kf)
        if len(guide[0]) and len(pts):
            from scipy.spatial import cKDTree  # teammates' guides only (not in slam-log)

            d, _ = cKDTree(guide[0]).query(pts, distance_upper_bound=GUIDE_OVERLAP_M)
            pts, nrm = pts[~np.isfinite(d)], nrm[~np.isfinite(d)]
        pts, nrm = np.concatenate([guide[0], pts]), np.concatenate([guide[1], nrm])
        if lm.voxel_m > 0:
            pts, nrm = voxel_mean(pts, nrm, lm.voxel_m)
        return PointMap(pts, nrm)

    def stand_still(self, stamp_ns: int) -> bool:
        return self.sweep.due(stamp_ns)

    def skip_stop(self) -> None:
        self.sweep.skip()


def _information_along(information: F64, v: F64) -> float:
    """A match's translation information along the unit direction ``v`` (its heading also
    estimated: the Schur complement, as in ``translation_degeneracy``)."""
    H = information
    Htt = H[:2, :2] - np.outer(H[:2, 2], H[2, :2]) / H[2, 2] if H[2, 2] > 0 else H[:2, :2]
    return float(v @ Htt @ v)


def _guide_points(slam: SlamView, T_map_robot: F64, radius_m: float) -> tuple[F64, F64] | None:
    """Points and normals (map frame) of the teammates' keyframes within ``radius_m`` of the
    robot, the teammates being those with a wide sensor that share ``slam``'s graph (another
    narrow sensor's map drifts as this one's does); None if there are none."""
    kfs: list[Keyframe] = []
    at: list[F64] = []
    for mate in slam.guides:
        if mate is slam or mate.graph is not slam.graph or not mate.keyframes or mate.narrow:
            continue
        poses = mate.keyframe_poses()
        near = np.flatnonzero(np.hypot(*(poses[:, :2] - T_map_robot[:2]).T) <= radius_m)
        kfs += [mate.keyframes[i] for i in near]
        at += [poses[i] for i in near]
    if not kfs:
        return None
    return gather(kfs, np.array(at))


def sensor_choice(cfg: SlamConfig) -> SensorChoice:
    """A robot's sensor models, the LIDAR's and the narrow sensor's. They share one set of
    square walls, which the LIDAR's keyframes join only with ``square_walls.narrow_only``
    off."""
    ties = HeadingTies(cfg.square_walls)
    lidar = LidarSensor(cfg, None if cfg.square_walls.narrow_only else ties)
    return SensorChoice(lidar, NarrowSensor(cfg, ties), cfg.matcher.narrow_fov_deg)
