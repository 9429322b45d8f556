"""``RobotSlam``: graph SLAM of one robot, fed one scan at a time (offline from a log, or live
by the server daemon). Its pose graph may be shared with other robots (see ``backend``)."""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from factors.scan_match import (
    heading_factor,
    loop_closure_factor,
    scan_match_factor,
    whitened_chi2,
)
from schemas.se2 import between, compose, pose_distance, transform_points, wrap_angle
from server.slam.backend import (
    FactorRecord,
    PoseGraph,
    RobotTrajectory,
    add_constraint,
    drop_constraint,
    extend_trajectory,
    start_trajectory,
)
from server.slam.config import SlamConfig, SweepConfig
from server.slam.errors import SlamInputError
from server.slam.frontend import (
    FrontendMatch,
    MatchKind,
    icp_params,
    is_narrow,
    match_scan,
    min_points,
    odometry_prior,
    odometry_step_suspicious,
)
from server.slam.grid import GridParams, OccupancyGrid
from server.slam.heading import SquareWalls, wall_direction, wrap_quarter
from server.slam.icp import PointMap
from server.slam.keyframes import Keyframe, gather, local_point_map, voxel_mean
from server.slam.loop_closure import LOOP_EDGE_LENGTH_M, LoopCloser, LoopClosure, LoopStats
from server.slam.mapping import GridMapper, point_cloud
from server.slam.scan import ScanPoints, field_of_view, scan_to_points
from server.slam.stamped import StampedRows
from server.slam.sweep import Sweep

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
IDENTITY = np.zeros(3)
#: a point of the robot's own map this close to a teammate's is left to the teammate's
GUIDE_OVERLAP_M = 0.15


@dataclass
class SlamStats:
    """Counters: scans accepted, keyframes, how each scan was matched, loop closures kept and
    taken out again."""

    scans: int = 0
    keyframes: int = 0
    matches: dict[str, int] = field(default_factory=lambda: {k.value: 0 for k in MatchKind})
    loop_closures: int = 0
    loop_closures_removed: int = 0
    reused: int = 0   # scans re-anchored on a keyframe instead of adding one (``reuse``)
    heading_ties: int = 0   # keyframes whose heading square walls tied (``square_walls``)
    sweeps: int = 0   # whole scans of a turning camera matched (``sweep``)


@dataclass(frozen=True)
class ScanPose:
    """Where a scan was, relative to the keyframe it was matched after."""

    stamp_ns: int
    keyframe: int
    T_kf_robot: F64


class RobotSlam:
    """Per-robot graph SLAM: predict → match → keyframe → optimise → loop closure → map.

    Feed it with ``add_scan`` once per scan (stamps must not go back in time; bad input raises
    ``SlamInputError`` and changes nothing). Read it with:

    - ``pose``: the latest robot pose (x, y, θ) in the map frame;
    - ``keyframes`` (``Keyframe``: index, stamp_ns, scan points in the robot frame) and
      ``keyframe_poses()`` (K, 3), the current optimised estimates;
    - ``scan_poses()``: stamps and optimised poses of every scan so far;
    - ``occupancy_grid()`` (incremental, re-rendered after the graph moved) and
      ``point_cloud()``;
    - ``trajectory`` (keys ``gtsam.symbol(robot_char, ...)``, the factors this robot added, its
      prior) and ``graph`` (the ``PoseGraph``, possibly shared with other robots).

    The map frame is the frame of ``T_map_start`` (default: the first pose is the origin).
    """

    def __init__(self, robot_char: str = "a", config: SlamConfig | None = None,
                 graph: PoseGraph | None = None,
                 T_map_start: ArrayLike = (0.0, 0.0, 0.0), key_block: int = 0) -> None:
        self.cfg = config or SlamConfig()
        c = self.cfg
        self.trajectory = RobotTrajectory(robot_char, key_block)
        self.graph = graph or PoseGraph(c.graph.relinearize_threshold)
        self.keyframes: list[Keyframe] = []
        self.stats = SlamStats()
        self._icp = icp_params(c.matcher)
        self._icp_narrow = dataclasses.replace(
            self._icp, min_normal_cos=c.matcher.narrow_min_normal_cos)
        self._loops = LoopCloser(c.loop, self._icp)
        self._mapper = GridMapper(GridParams(**c.grid.model_dump()))
        self._T_map_start = np.asarray(T_map_start, dtype=np.float64)
        self._scan_poses = StampedRows(3)   # per scan: stamp, keyframe, pose in its frame
        self._local_map: PointMap | None = None
        self._last_odom: F64 | None = None
        self._last_stamp_ns: int | None = None
        self._T_kf_robot = IDENTITY.copy()  # the robot relative to its anchor keyframe
        self._anchor = 0                    # the newest keyframe, or one re-used (``reuse``)
        self._T_kf_moved_from = IDENTITY.copy()   # where the anchor was last taken up
        self.reusing = False                # re-use keyframes where the robot passes again
        self._T_kf_map_cache: F64 = self._T_map_start.copy()
        self._velocity = IDENTITY.copy()  # last scan-to-scan motion (robot frame)
        #: a narrow sensor's latest matches (anchor key, pose from it, information in the
        #: robot frame, odometry), averaged
        self._recent: list[tuple[int, F64, F64, F64]] = []
        self.narrow = False            # the latest scan was narrow (a depth camera's)
        #: teammates sharing this graph, whose maps a narrow sensor matches against (set by
        #: the server before each scan; not kept in a snapshot)
        self.guides: list[RobotSlam] = []
        self._square = self._square_walls()
        self._sweep = Sweep(c.sweep)
        self._wholes: list[int] = []    # keyframes of a turning camera's whole scans

    def _square_walls(self) -> SquareWalls:
        c = self.cfg.square_walls
        return SquareWalls(c.min_points, c.min_alignment, c.agree_deg, c.max_correction_deg,
                           c.min_checked, c.min_agreement, c.partners)

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "guides": []}   # the teammates are the fleet's to keep

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update({"guides": [], "narrow": False, "_recent": [], "_wholes": [],
                              **state})
        if "_square" not in state:        # saved before square walls held the heading
            self._square = self._square_walls()
        if "_sweep" not in state:         # saved before a turning camera's whole scans
            self._sweep = Sweep(getattr(self.cfg, "sweep", SweepConfig()))
        if "_icp_narrow" not in state:   # saved before narrow scans had their own
            self._icp_narrow = dataclasses.replace(
                self._icp, min_normal_cos=self.cfg.matcher.narrow_min_normal_cos)

    # -- the method ----------------------------------------------------------------------
    def add_scan(self, stamp_ns: int, odom_pose_xyt: ArrayLike, ranges_m: ArrayLike,
                 angles_rad: ArrayLike, sensor_max_range_m: float | None = None) -> F64:
        """Process one scan; returns the robot pose (x, y, θ) in the map frame.

        ``odom_pose_xyt`` is the wheel-odometry pose at the scan's time; ranges that are not
        finite (or outside the configured range) are beams without a return. Given the
        sensor's maximum range, such beams (+inf) also mark free space up to
        ``min(scan.no_return_free_m, sensor_max_range_m)``.
        """
        odom = self._check_input(stamp_ns, odom_pose_xyt)
        scan = self._scan_points(ranges_m, angles_rad, sensor_max_range_m)
        self.narrow = is_narrow(scan, self.cfg.matcher)
        if not self.keyframes:
            self._first_keyframe(stamp_ns, scan, odom)
            return self.pose
        T_last = self.pose
        assert self._last_odom is not None
        step = between(self._last_odom, odom)
        T_pred = compose(T_last, step)                                 # 1. predict (odometry)
        match = self._match(scan, T_pred, T_last, step)                # 2. match the local map
        whole: int | None = None
        if is_narrow(scan, self.cfg.matcher):                          # (a narrow sensor's
            scan, match, whole = self._narrow(scan, match, odom, T_pred, T_last, step)
        self._velocity = between(T_last, match.T_map_robot)
        self._T_kf_robot = between(self._T_kf_map_cache, match.T_map_robot)
        self._last_odom, self._last_stamp_ns = odom, stamp_ns
        if whole is not None or self._is_keyframe(scan, match.T_map_robot):   # 3. keyframe?
            j = (self._reusable(match.T_map_robot) if self.reusing and whole is None
                 else None)
            if j is not None:                                          # (or one re-used)
                self._reanchor(j, match.T_map_robot)
            else:
                k = self._add_keyframe(stamp_ns, scan, odom, match, whole)   # 4. optimise
                if self.cfg.loop.enabled and k % self.cfg.loop.every_keyframes == 0:
                    self._close_loops(k)                               # 5. loop closure
                self._refresh_local_map()                              # 6. maps follow poses
        self._scan_poses.append(stamp_ns, self._T_kf_robot, tag=self._anchor)
        self.stats.scans += 1
        return self.pose

    # -- steps ---------------------------------------------------------------------------
    def _check_input(self, stamp_ns: int, odom_pose_xyt: ArrayLike) -> F64:
        odom = np.asarray(odom_pose_xyt, dtype=np.float64).reshape(-1)
        if odom.shape != (3,) or not np.all(np.isfinite(odom)):
            raise SlamInputError(f"odometry pose must be 3 finite numbers, got {odom!r}")
        if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            raise SlamInputError(f"scan stamp {stamp_ns} is older than the previous "
                                 f"({self._last_stamp_ns})")
        return odom

    def _scan_points(self, ranges_m: ArrayLike, angles_rad: ArrayLike,
                     sensor_max_range_m: float | None = None) -> ScanPoints:
        s = self.cfg.scan
        free_m = 0.0
        if sensor_max_range_m is not None and math.isfinite(sensor_max_range_m):
            free_m = max(0.0, min(s.no_return_free_m, sensor_max_range_m))
        angles = np.asarray(angles_rad, dtype=np.float64)
        narrow = field_of_view(angles)[0] < math.radians(self.cfg.matcher.narrow_fov_deg)
        return scan_to_points(np.asarray(ranges_m, dtype=np.float64), angles, s.min_range_m,
                              s.max_range_m, s.narrow_normal_window if narrow else s.normal_window,
                              s.normal_max_gap_m, s.min_point_spacing_m, free_m)

    def _narrow(self, scan: ScanPoints, match: FrontendMatch, odom: F64, T_pred: F64,
                T_last: F64, step: F64) -> tuple[ScanPoints, FrontendMatch, int | None]:
        """A narrow scan's match, averaged over the latest (``_smoothed``); or, when it
        completes a turning camera's views taken while the robot stood still, those views as
        one 360° scan (``server.slam.sweep``), which then stands for it and becomes a
        keyframe. The third value is None for a narrow scan; for a whole one, the keyframe
        of the whole scan before it that it was matched against, or -1."""
        whole = self._sweep.add(scan, odom) if self._sweep.cfg.enabled else None
        mc = self.cfg.matcher
        if whole is None or len(whole) < mc.min_points:
            return scan, self._smoothed(match, odom), None
        def prior(step: F64) -> F64 | None:
            return odometry_prior(step, mc) if mc.use_odometry_prior else None

        # against the whole scans before it: they were taken standing still, so what they
        # drew is not smeared by the narrow views' drift
        prev = self._wholes[-1] if self._wholes else None
        if prev is not None:
            kfs = [self.keyframes[i] for i in self._wholes[-3:]]
            poses = self.graph.poses([self.trajectory.key(kf.index) for kf in kfs])
            target = local_point_map(kfs, poses, self.cfg.local_map.voxel_m)
            from_prev = between(self.keyframes[prev].T_odom_robot, odom)
            T_guess = compose(poses[-1], from_prev)
            if len(target) >= mc.min_points:
                m = match_scan(whole, target, T_guess, T_guess, IDENTITY, False, mc, self._icp,
                               prior(from_prev))
                d, a = pose_distance(between(T_guess, m.T_map_robot))
                if m.kind in (MatchKind.ICP, MatchKind.DEGENERATE) and \
                        d <= self._sweep.cfg.max_shift_m and \
                        a <= math.radians(self._sweep.cfg.max_turn_deg):
                    self.stats.sweeps += 1
                    self._recent.clear()      # the whole scan outweighs the views before it
                    return whole, self._smoothed(m, odom), prev
                # a match far from the odometry's is a wall taken for another: the local
                # map, drawn by the narrow views, would not say better
                return whole, self._smoothed(match, odom), -1
        assert self._local_map is not None
        m = match_scan(whole, self._local_map, T_pred, T_last, self._velocity, False, mc,
                       self._icp, prior(step))
        if m.kind in (MatchKind.ICP, MatchKind.DEGENERATE):
            self.stats.sweeps += 1
            self._recent.clear()
            return whole, self._smoothed(m, odom), -1
        # unmatched (it sees mostly what the map has not): still the better keyframe
        return whole, self._smoothed(match, odom), -1

    def sweep_due(self, stamp_ns: int) -> bool:
        """Whether the robot should stand still now while its turning camera makes a whole
        scan (``server.slam.sweep``; never for a 360° sensor or a camera that does not
        turn)."""
        return self.narrow and self._sweep.due(stamp_ns)

    def _smoothed(self, match: FrontendMatch, odom: F64) -> FrontendMatch:
        """A narrow scan's pose from every match since the last keyframe, each carried here by
        odometry and weighed by its information (less the farther it was carried): one narrow
        scan of a noisy depth camera pins the heading to a degree or so, and a keyframe placed
        on one such match passes that error on to the whole map. The matches are kept
        relative to their anchor keyframe, so they follow it when the graph moves it."""
        g = self.cfg.graph
        anchor = self.trajectory.key(self._anchor)
        if match.kind in (MatchKind.ICP, MatchKind.DEGENERATE):
            T = match.T_map_robot
            R = _rotation(T[2])
            self._recent.append((anchor, between(self._T_kf_map_cache, T),
                                 R.T @ match.information @ R, odom))
        del self._recent[:-self.cfg.matcher.narrow_smoothing]
        if match.kind == MatchKind.ODOMETRY or len(self._recent) < 2:
            return match
        T0 = match.T_map_robot
        H, b = np.zeros((3, 3)), np.zeros(3)
        for key, T_kf_j, info_robot, odom_j in self._recent:
            T_j = compose(self.graph.pose(key), T_kf_j)
            R = _rotation(T_j[2])
            carried = between(odom_j, odom)
            d, a = pose_distance(carried)
            s_xy = g.odometry_sigma_m_per_m * d + 1e-3
            s_th = math.radians(g.odometry_sigma_deg_per_rad * a) + 1e-4
            cov = np.linalg.inv(R @ info_robot @ R.T + 1e-6 * np.eye(3))  # ~1e6: unseen
            info = np.linalg.inv(cov + np.diag([s_xy ** 2, s_xy ** 2, s_th ** 2]))
            T = compose(T_j, carried)
            e = np.array([T[0] - T0[0], T[1] - T0[1], wrap_angle(T[2] - T0[2])])
            H += info
            b += info @ e
        if not H.any():
            return match
        delta = np.linalg.solve(H + 1e-9 * np.eye(3), b)
        T = T0 + delta
        T[2] = wrap_angle(T[2])
        return FrontendMatch(T, match.kind, match.information, match.inlier_fraction)

    def _first_keyframe(self, stamp_ns: int, scan: ScanPoints, odom: F64) -> None:
        g = self.cfg.graph
        prior = np.array([g.prior_sigma_m, g.prior_sigma_m, math.radians(g.prior_sigma_deg)])
        start_trajectory(self.graph, self.trajectory, self._T_map_start, prior)
        self.keyframes.append(Keyframe.create(0, stamp_ns, scan, odom,
                                              self.cfg.keyframes.render_on_disk))
        self._last_odom, self._last_stamp_ns = odom, stamp_ns
        self._T_kf_map_cache = self._T_map_start.copy()
        self._scan_poses.append(stamp_ns, IDENTITY, tag=0)
        self.stats.scans += 1
        self.stats.keyframes = 1
        self._refresh_local_map()

    def _match(self, scan: ScanPoints, T_pred: F64, T_last: F64, step: F64) -> FrontendMatch:
        assert self._local_map is not None
        mc = self.cfg.matcher
        prior = odometry_prior(step, mc, is_narrow(scan, mc)) if mc.use_odometry_prior else None
        m = match_scan(scan, self._local_map, T_pred, T_last, self._velocity,
                       odometry_step_suspicious(step, mc), mc,
                       self._icp_narrow if is_narrow(scan, mc) else self._icp, prior)
        self.stats.matches[m.kind.value] += 1
        return m

    def _is_keyframe(self, scan: ScanPoints, T_map_robot: F64) -> bool:
        # motion since the anchor was taken up (a re-used keyframe may face elsewhere)
        d, a = pose_distance(between(self._T_kf_moved_from, self._T_kf_robot))
        k = self.cfg.keyframes
        if d >= k.distance_m or a >= math.radians(k.angle_deg):
            return True
        # nothing to match against yet (e.g. the first scans had no returns): take this one
        n = min_points(scan, self.cfg.matcher)
        local = self._local_map
        if local is not None and len(local) < n <= len(scan):
            return True
        # a narrow sensor looking where the local map has nothing yet
        if local is None or len(scan) < n or not is_narrow(scan, self.cfg.matcher):
            return False
        d_near, _ = local.tree.query(transform_points(T_map_robot, scan.points),
                                     distance_upper_bound=k.novel_m)
        return float(np.mean(~np.isfinite(d_near))) >= k.novel_fraction

    def _relative_information(self, match: FrontendMatch, T_rel: F64) -> F64:
        """Information of the keyframe-to-keyframe measurement in the new keyframe's frame:
        the match's (rotated from the map frame) plus odometry's, which keeps degenerate
        directions constrained."""
        g = self.cfg.graph
        A = _rotation(match.T_map_robot[2])
        info = A.T @ match.information @ A if match.kind != MatchKind.ODOMETRY else np.zeros((3, 3))
        d, a = pose_distance(T_rel)
        s_xy = g.odometry_sigma_m_per_m * d + g.match_sigma_floor_m
        s_th = math.radians(g.odometry_sigma_deg_per_rad * a + g.match_sigma_floor_deg)
        return info + np.diag([s_xy ** -2, s_xy ** -2, s_th ** -2])

    def _add_keyframe(self, stamp_ns: int, scan: ScanPoints, odom: F64,
                      match: FrontendMatch, whole: int | None = None) -> int:
        """Keyframe k after the anchor; ``whole`` (see ``_narrow``): for a whole scan matched
        against the whole scans before it, that match ties it to the latest of them, and
        the anchor only by odometry."""
        g = self.cfg.graph
        k = len(self.keyframes)
        T_rel = self._T_kf_robot.copy()
        tr = self.trajectory
        floor = np.array([g.match_sigma_floor_m, g.match_sigma_floor_m,
                          math.radians(g.match_sigma_floor_deg)])
        scale = g.match_cov_scale if match.kind != MatchKind.ODOMETRY else 1.0
        a = self._anchor
        by = (FrontendMatch(match.T_map_robot, MatchKind.ODOMETRY, np.zeros((3, 3)), 0.0)
              if whole is not None and whole >= 0 else match)
        factor = scan_match_factor(tr.key(a), tr.key(k), T_rel,
                                   self._relative_information(by, T_rel),
                                   scale if by is match else 1.0, floor)
        kind = "odometry" if by.kind == MatchKind.ODOMETRY else "match"
        extend_trajectory(self.graph, tr, factor, kind, match.T_map_robot)
        if whole is not None and whole >= 0:
            T_w = between(self.graph.pose(tr.key(whole)), match.T_map_robot)
            add_constraint(self.graph, tr, scan_match_factor(
                tr.key(whole), tr.key(k), T_w, self._relative_information(match, T_w), scale,
                floor), "sweep")
            self._loops.add_edge(whole, k, pose_distance(T_w)[0] + 0.2 * pose_distance(T_w)[1])
        if whole is not None:
            self._wholes.append(k)
        self.keyframes.append(Keyframe.create(k, stamp_ns, scan, odom,
                                              self.cfg.keyframes.render_on_disk))
        self.stats.keyframes = len(self.keyframes)
        if whole is not None and self._square.reference is None:
            self._reference_walls(scan, odom)
        self._tie_heading(k, scan, match.T_map_robot)
        self._loops.add_edge(a, k, pose_distance(T_rel)[0] + 0.2 * pose_distance(T_rel)[1])
        self._anchor = k
        self._T_kf_robot = IDENTITY.copy()
        self._T_kf_moved_from = IDENTITY.copy()
        self._T_kf_map_cache = self.graph.pose(tr.key(k))
        return k

    def _reference_walls(self, whole: ScanPoints, odom: F64) -> None:
        """A whole scan taken before the robot moved from its first pose gives the first
        keyframe's wall direction far better than any narrow view: square-wall ties then all
        hold to the first keyframe through it (``SquareWalls.reference``)."""
        c, sw = self.cfg.square_walls, self._sweep.cfg
        d, a = pose_distance(between(self.keyframes[0].T_odom_robot, odom))
        if d > sw.still_m or a > math.radians(sw.still_deg):
            return
        found = wall_direction(whole.normals, c.min_points)
        if found is None or found[1] < c.min_alignment:
            return
        turned = wrap_angle(odom[2] - self.keyframes[0].T_odom_robot[2])
        self._square.reference = (0, wrap_quarter(found[0] + turned))

    def _tie_heading(self, k: int, scan: ScanPoints, T_map_robot: F64) -> None:
        """Tie keyframe ``k``'s heading to earlier keyframes' where square walls say what it
        is (``server.slam.heading``)."""
        c = self.cfg.square_walls
        if not c.enabled or (c.narrow_only and not self.narrow):
            return
        tr = self.trajectory
        poses: dict[int, F64] = {}    # the earlier keyframes' estimates, each read once

        def rel(j: int) -> float:
            poses[j] = self.graph.pose(tr.key(j))
            return float(wrap_angle(T_map_robot[2] - poses[j][2]))

        ties = self._square.observe(k, scan.normals, rel)
        ref = self._square.reference
        others = sum(ref is None or j != ref[0] for j, _ in ties)
        sigma = math.radians(c.sigma_deg) * math.sqrt(max(others, 1))
        for j, heading in ties:
            T = between(poses[j], T_map_robot)
            T[2] = heading
            s = math.radians(c.sigma_deg) if ref is not None and j == ref[0] else sigma
            add_constraint(self.graph, tr, heading_factor(tr.key(j), tr.key(k), T, s,
                                                          c.huber_k), "heading")
        if ties:
            self.stats.heading_ties += 1

    def _close_loops(self, k: int) -> None:
        poses = self.keyframe_poses()
        self._loops.maybe_close_submap(self.keyframes, poses)
        closures = self._loops.search(k, self.keyframes, poses, self.narrow)
        if closures:
            self.apply_loop_closures(closures)

    def apply_loop_closures(self, closures: list[LoopClosure]) -> int:
        """Add verified closures under a robust kernel, optimise, and take out again any whose
        error is still implausible (χ² > ``max_chi2``) once the graph has settled. Returns how
        many were kept."""
        c, g = self.cfg.loop, self.cfg.graph
        tr = self.trajectory
        floor = np.array([g.match_sigma_floor_m, g.match_sigma_floor_m,
                          math.radians(g.match_sigma_floor_deg)])
        added: list[tuple[LoopClosure, FactorRecord]] = []
        for lc in closures:
            f = loop_closure_factor(tr.key(lc.anchor), tr.key(lc.keyframe), lc.T_anchor_kf,
                                    lc.information, c.sigma_scale ** 2, floor, "huber", c.huber_k)
            added.append((lc, add_constraint(self.graph, tr, f, "loop")))
        self.graph.iterate(g.extra_iterations_after_loop)
        est = self.graph.estimate()
        kept = 0
        removed = False
        for lc, rec in added:
            chi2 = whitened_chi2(rec.factor, est)
            if chi2 > c.max_chi2:
                log.info("loop closure %d-%d removed: χ² %.1f after optimisation",
                         lc.anchor, lc.keyframe, chi2)
                drop_constraint(self.graph, tr, rec)
                self._loops.stats.removed_inconsistent += 1
                self.stats.loop_closures_removed += 1
                removed = True
            else:
                self._loops.add_edge(lc.anchor, lc.keyframe, LOOP_EDGE_LENGTH_M)
                self.stats.loop_closures += 1
                kept += 1
        if removed:
            self.graph.iterate(g.extra_iterations_after_loop)
        self._T_kf_map_cache = self.graph.pose(tr.key(self._anchor))
        return kept

    def _refresh_local_map(self) -> None:
        lm = self.cfg.local_map
        n = lm.narrow_keyframes if self.narrow else lm.keyframes
        if self.reusing:   # the keyframes nearest the anchor: the recent ones may be far
            poses = self.keyframe_poses()
            d = np.hypot(*(poses[:, :2] - poses[self._anchor, :2]).T)
            picked = np.sort(np.argsort(d, kind="stable")[:n])
            kfs = [self.keyframes[i] for i in picked]
            self._local_map = local_point_map(kfs, poses[picked], self.cfg.local_map.voxel_m)
            return
        kfs = self.keyframes[-n:]
        keys = [self.trajectory.key(kf.index) for kf in kfs]
        poses = self.graph.poses(keys)
        guide = (self._guide_points(poses[-1])
                 if self.narrow and self.guides and self.cfg.local_map.guide_radius_m > 0
                 else None)
        if guide is None:
            self._local_map = local_point_map(kfs, poses, self.cfg.local_map.voxel_m)
            return
        pts, nrm = gather(kfs, poses)
        if len(guide[0]) and len(pts):   # the teammates' walls where they have them
            d, _ = cKDTree(guide[0]).query(pts, distance_upper_bound=GUIDE_OVERLAP_M)
            pts, nrm = pts[~np.isfinite(d)], nrm[~np.isfinite(d)]
        pts, nrm = np.concatenate([guide[0], pts]), np.concatenate([guide[1], nrm])
        if self.cfg.local_map.voxel_m > 0:
            pts, nrm = voxel_mean(pts, nrm, self.cfg.local_map.voxel_m)
        self._local_map = PointMap(pts, nrm)

    def _guide_points(self, T_map_robot: F64) -> tuple[F64, F64] | None:
        """Points and normals of the teammates' keyframes (``guides``, in this graph) within
        ``local_map.guide_radius_m`` of the robot: a narrow sensor matches against the map
        its team's wide sensors drew where they drew it."""
        r = self.cfg.local_map.guide_radius_m
        kfs: list[Keyframe] = []
        at: list[F64] = []
        for g in self.guides:
            if g is self or g.graph is not self.graph or not g.keyframes:
                continue
            poses = g.keyframe_poses()
            near = np.flatnonzero(np.hypot(*(poses[:, :2] - T_map_robot[:2]).T) <= r)
            kfs += [g.keyframes[i] for i in near]
            at += [poses[i] for i in near]
        if not kfs:
            return None
        return gather(kfs, np.array(at))

    def _reusable(self, T_map_robot: F64) -> int | None:
        """A keyframe other than the anchor where the robot is now (``keyframes.reuse_m`` and
        ``reuse_deg``), the nearest; None if there is none."""
        k = self.cfg.keyframes
        poses = self.keyframe_poses()
        d = np.hypot(poses[:, 0] - T_map_robot[0], poses[:, 1] - T_map_robot[1])
        turn = np.abs(wrap_angle(poses[:, 2] - T_map_robot[2]))
        ok = (d <= k.reuse_m) & (turn <= math.radians(k.reuse_deg))
        ok[self._anchor] = False
        if not ok.any():
            return None
        return int(np.flatnonzero(ok)[np.argmin(d[ok])])

    def _reanchor(self, j: int, T_map_robot: F64) -> None:
        """Go on from keyframe ``j`` (the robot is where it was taken) instead of a new one."""
        self._anchor = j
        self._T_kf_map_cache = self.graph.pose(self.trajectory.key(j))
        self._T_kf_robot = between(self._T_kf_map_cache, T_map_robot)
        self._T_kf_moved_from = self._T_kf_robot.copy()
        self.stats.reused += 1
        self._refresh_local_map()

    def rebind(self, graph: PoseGraph) -> None:
        """Continue in ``graph`` (which now holds this robot's keys, e.g. a team's joint
        problem in the team's frame): cached map-frame poses and the local map follow."""
        self.graph = graph
        if self.keyframes:
            self._T_kf_map_cache = graph.pose(self.trajectory.key(self._anchor))
            self._refresh_local_map()

    def pose_at(self, stamp_ns: int, tolerance_ns: int = 150_000_000
                ) -> tuple[int, F64] | None:
        """Where the robot was at ``stamp_ns``: a keyframe index and the robot's pose relative
        to that keyframe, interpolated between the scans around that instant. None when no
        scan is close enough, and — later than the newest scan — until the next scan is in
        (a robot turning at 1.5 rad/s turns 9° in one scan period: the pose of the scan before
        is not the pose at the sighting). Before the first scan, the first within
        ``tolerance_ns``; across a gap in the scans (dropped while the server was behind)
        wider than 2 × ``tolerance_ns``, the nearest within a third of it."""
        sp = self._scan_poses
        if not len(sp):
            return None
        stamps = sp.stamps
        i = int(np.searchsorted(stamps, stamp_ns, side="left"))
        if i < len(sp) and stamps[i] == stamp_ns:
            return int(sp.tags[i]), sp.values[i].copy()
        if i == len(sp):
            return None
        if i == 0:
            if int(stamps[0]) - stamp_ns > tolerance_ns:
                return None
            return int(sp.tags[0]), sp.values[0].copy()
        a, b = ScanPose(*sp.row(i - 1)), ScanPose(*sp.row(i))
        if b.stamp_ns - a.stamp_ns > 2 * tolerance_ns:
            near = a if stamp_ns - a.stamp_ns <= b.stamp_ns - stamp_ns else b
            if abs(near.stamp_ns - stamp_ns) > tolerance_ns // 3:
                return None
            return near.keyframe, near.T_kf_robot.copy()
        f = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        keys = [self.trajectory.key(a.keyframe), self.trajectory.key(b.keyframe)]
        Xa, Xb = self.graph.poses(keys)
        Pa, Pb = compose(Xa, a.T_kf_robot), compose(Xb, b.T_kf_robot)
        step = between(Pa, Pb)
        return a.keyframe, compose(a.T_kf_robot, step * f)

    def pose_sigma(self) -> tuple[float, float, float]:
        """σ of the newest keyframe's pose (x, y [m] and θ [rad], in its own frame), from
        the graph's marginal covariance."""
        cov = self.graph.marginal_covariance(self.trajectory.key(len(self.keyframes) - 1))
        s = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return float(s[0]), float(s[1]), float(s[2])

    def keyframe_pose(self, index: int) -> F64:
        """The optimised pose of one keyframe."""
        return self.graph.pose(self.trajectory.key(index))

    # -- accessors -----------------------------------------------------------------------
    @property
    def robot_char(self) -> str:
        return self.trajectory.robot_char

    @property
    def pose(self) -> F64:
        """Current robot pose (x, y, θ) in the map frame."""
        return compose(self._T_kf_map_cache, self._T_kf_robot)

    def keyframe_poses(self) -> F64:
        """Optimised poses (K, 3) of all keyframes, in keyframe order."""
        return self.graph.poses(self.trajectory.all_keys())

    def scan_poses(self) -> tuple[NDArray[np.int64], F64]:
        """Stamps [ns] and optimised map-frame poses (N, 3) of every scan added so far."""
        kf_poses = self.keyframe_poses()
        sp = self._scan_poses
        if not len(sp):
            return sp.stamps.copy(), np.zeros((0, 3))
        return sp.stamps.copy(), compose(kf_poses[sp.tags], sp.values)

    def occupancy_grid(self) -> OccupancyGrid:
        """The occupancy grid at the current poses (incremental, or re-rendered if they moved)."""
        return self._mapper.update(self.keyframes, self.keyframe_poses())

    def point_cloud(self, voxel_m: float = 0.05) -> F64:
        """Keyframe points (N, 2) in the map frame, one per ``voxel_m`` cell."""
        return point_cloud(self.keyframes, self.keyframe_poses(), voxel_m)

    @property
    def loop_stats(self) -> LoopStats:
        """Counters of the loop-closure search (candidates, rejections by reason...)."""
        return self._loops.stats


def _rotation(theta: float) -> F64:
    """The 3×3 rotation of (x, y, θ) vectors by ``theta``."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
