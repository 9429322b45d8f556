"""``RobotSlam``: graph SLAM of one robot, fed one scan at a time (offline from a log, or live
by the server daemon). Its pose graph may be shared with other robots (see ``backend``).

The pipeline is the same for every sensor; what one kind of sensor needs besides is its
``SensorModel`` (``server.slam.sensor``: a 360° LIDAR's; ``server.slam.narrow``: a depth
camera's), which each scan picks by its field of view."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from schemas.se2 import between, compose
from server.slam.backend import PoseGraph, RobotTrajectory, extend_trajectory, start_trajectory
from server.slam.closures import add_loop_closures
from server.slam.config import SlamConfig
from server.slam.errors import SlamInputError
from server.slam.frontend import MatchKind, icp_params, min_points
from server.slam.grid import GridParams, OccupancyGrid
from server.slam.icp import PointMap
from server.slam.keyframes import Keyframe, local_point_map, nearest_keyframes, reusable_keyframe
from server.slam.loop_closure import LoopCloser, LoopClosure, LoopStats, edge_length_m
from server.slam.mapping import GridMapper, point_cloud
from server.slam.measurements import match_factor, odometry_only
from server.slam.narrow import sensor_choice
from server.slam.scan import ScanPoints
from server.slam.scan_poses import Anchor, ScanPoses
from server.slam.sensor import SensorModel
from server.slam.view import Placement, SlamStats

F64 = NDArray[np.float64]
IDENTITY = np.zeros(3)

__all__ = ["RobotSlam", "SlamStats"]


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
      prior) and ``graph`` (the ``PoseGraph``, possibly shared with other robots);
    - ``narrow`` and ``sweep_due``: what the latest scan's sensor model says.

    The map frame is the frame of ``T_map_start`` (default: the first pose is the origin).
    """

    # keyframes' matching points in single precision (``slam-log``); a class default, so that
    # a SLAM pickled before it was added has it too
    single_keyframes = False

    def __init__(self, robot_char: str = "a", config: SlamConfig | None = None,
                 graph: PoseGraph | None = None,
                 T_map_start: ArrayLike = (0.0, 0.0, 0.0), key_block: int = 0) -> None:
        self.cfg = config or SlamConfig()
        c = self.cfg
        self.trajectory = RobotTrajectory(robot_char, key_block)
        self.graph = graph or PoseGraph(c.graph.relinearize_threshold)
        self.keyframes: list[Keyframe] = []
        self.stats = SlamStats()
        self.loops = LoopCloser(c.loop, icp_params(c.matcher))
        self._mapper = GridMapper(GridParams(**c.grid.model_dump()))
        self._T_map_start = np.asarray(T_map_start, dtype=np.float64)
        self._scan_poses = ScanPoses()
        self._last_odom: F64 | None = None
        self._last_stamp_ns: int | None = None
        self.anchor = Anchor(0, self._T_map_start.copy())
        self.local_map: PointMap | None = None   # what the next scan is matched against
        self.velocity = IDENTITY.copy()  # the last scan-to-scan motion (x, y, θ), robot frame
        self.reusing = False                # re-use keyframes where the robot passes again
        self._sensors = sensor_choice(c)
        self.sensor: SensorModel = self._sensors.wide   # the latest scan's
        #: teammates sharing this graph, whose maps a narrow sensor matches against (set by
        #: the server before each scan; not kept in a snapshot)
        self.guides: list[RobotSlam] = []

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "guides": []}   # the teammates are the fleet's to keep

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
        scan = self._prepare(ranges_m, angles_rad, sensor_max_range_m)  # 0. points, normals
        if not self.keyframes:
            self._first_keyframe(stamp_ns, scan, odom)
            return self.pose
        T_last = self.pose
        assert self._last_odom is not None and self.local_map is not None
        step = between(self._last_odom, odom)
        T_pred = compose(T_last, step)                                 # 1. predict (odometry)
        match = self.sensor.match(scan, self.local_map, T_pred, T_last, self.velocity, step)
        self.stats.matches[match.kind.value] += 1                      # 2. match the local map
        # 3. the sensor's say (a narrow view's pose averaged, or a whole scan it completed)
        placed = self.sensor.place(self, scan, match, odom, T_pred, T_last, step)
        T_map_robot = placed.match.T_map_robot
        self.velocity = between(T_last, T_map_robot)
        self.anchor.T_kf_robot = between(self.anchor.T_map_kf, T_map_robot)
        self._last_odom, self._last_stamp_ns = odom, stamp_ns
        if placed.whole or self._is_keyframe(placed.scan, T_map_robot):   # 4. keyframe?
            j = self._reusable(T_map_robot) if self.reusing and not placed.whole else None
            if j is not None:                                          # (or one re-used)
                self.anchor = Anchor.taken_up(j, self.keyframe_pose(j), T_map_robot)
                self.stats.reused += 1
            else:
                k = self._add_keyframe(stamp_ns, odom, placed)         # 5. optimise
                if self.cfg.loop.enabled and k % self.cfg.loop.every_keyframes == 0 \
                        and not self._beside_a_wide_teammate():
                    self._close_loops(k)                               # 6. loop closure
            self._refresh_local_map()                                  # 7. maps follow poses
        self._scan_poses.append(stamp_ns, self.anchor.index, self.anchor.T_kf_robot)
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

    def _prepare(self, ranges_m: ArrayLike, angles_rad: ArrayLike,
                 sensor_max_range_m: float | None) -> ScanPoints:
        """The scan's points and normals, by the sensor model its field of view calls for,
        which becomes the robot's ``sensor`` (unless the scan is refused). Beams without a
        return mark free space only as far as the sensor's range is known."""
        free_m = 0.0
        if sensor_max_range_m is not None and math.isfinite(sensor_max_range_m):
            free_m = max(0.0, min(self.cfg.scan.no_return_free_m, sensor_max_range_m))
        angles = np.asarray(angles_rad, dtype=np.float64)
        sensor = self._sensors.for_angles(angles)
        scan = sensor.prepare(np.asarray(ranges_m, dtype=np.float64), angles, free_m)
        self.sensor = sensor
        return scan

    def _first_keyframe(self, stamp_ns: int, scan: ScanPoints, odom: F64) -> None:
        g = self.cfg.graph
        prior = np.array([g.prior_sigma_m, g.prior_sigma_m, math.radians(g.prior_sigma_deg)])
        start_trajectory(self.graph, self.trajectory, self._T_map_start, prior)
        self.keyframes.append(Keyframe.create(0, stamp_ns, scan, odom,
                                              self.cfg.keyframes.render_on_disk,
                                              self.single_keyframes))
        self._last_odom, self._last_stamp_ns = odom, stamp_ns
        self.anchor = Anchor(0, self._T_map_start.copy())
        self._scan_poses.append(stamp_ns, 0, IDENTITY)
        self.stats.scans += 1
        self.stats.keyframes = 1
        self._refresh_local_map()

    def _is_keyframe(self, scan: ScanPoints, T_map_robot: F64) -> bool:
        # motion since the anchor was taken up (a re-used keyframe may face elsewhere)
        d, a = self.anchor.moved()
        k = self.cfg.keyframes
        if d >= k.distance_m or a >= math.radians(k.angle_deg):
            return True
        # nothing to match against yet (e.g. the first scans had no returns): take this one
        n = min_points(scan, self.cfg.matcher)
        local = self.local_map
        if local is not None and len(local) < n <= len(scan):
            return True
        if local is None or len(scan) < n:
            return False
        return self.sensor.sees_new(scan, T_map_robot, local)

    def _add_keyframe(self, stamp_ns: int, odom: F64, placed: Placement) -> int:
        """Keyframe k after the anchor, tied to it by the match (or by odometry alone, when
        the sensor model matched the scan against another keyframe: it adds that factor)."""
        k, a = len(self.keyframes), self.anchor.index
        tr, match = self.trajectory, placed.match
        T_rel = self.anchor.T_kf_robot.copy()
        by = odometry_only(match) if placed.matched_to is not None else match
        kind = "odometry" if by.kind == MatchKind.ODOMETRY else "match"
        extend_trajectory(self.graph, tr, match_factor(tr.key(a), tr.key(k), T_rel, by,
                                                       self.cfg.graph), kind, match.T_map_robot)
        self.keyframes.append(Keyframe.create(k, stamp_ns, placed.scan, odom,
                                              self.cfg.keyframes.render_on_disk,
                                              self.single_keyframes))
        self.stats.keyframes = len(self.keyframes)
        self.sensor.on_keyframe(self, k, placed, odom)
        self.loops.add_edge(a, k, edge_length_m(T_rel))
        self.anchor = Anchor(k, self.keyframe_pose(k))
        return k

    def _beside_a_wide_teammate(self) -> bool:
        """A narrow sensor's robot in one graph with a wide one: the teammate's map holds it
        (``server.rendezvous.surgery``), and a loop closed on its own drifting keyframes
        could only pull it off that map (0.34 m at once, on a keyframe of a turning stop)."""
        return self.sensor.narrow and any(not g.narrow and g.graph is self.graph
                                          for g in self.guides)

    def _close_loops(self, k: int) -> None:
        poses = self.keyframe_poses()
        self.loops.maybe_close_submap(self.keyframes, poses)
        closures = self.loops.search(k, self.keyframes, poses, self.sensor.narrow)
        if closures:
            self.apply_loop_closures(closures)

    def apply_loop_closures(self, closures: list[LoopClosure]) -> int:
        """Add verified closures, optimise, and take out again any the settled graph finds
        implausible (``server.slam.closures``). Returns how many were kept."""
        kept, removed = add_loop_closures(self.graph, self.trajectory, self.loops, closures,
                                          self.cfg.loop, self.cfg.graph)
        self.stats.loop_closures += kept
        self.stats.loop_closures_removed += removed
        self.anchor.T_map_kf = self.keyframe_pose(self.anchor.index)
        return kept

    def _refresh_local_map(self) -> None:
        n = self.sensor.local_keyframes
        if self.reusing:   # the keyframes nearest the anchor: the recent ones may be far
            poses = self.keyframe_poses()
            picked = nearest_keyframes(poses, self.anchor.index, n)
            kfs = [self.keyframes[i] for i in picked]
            self.local_map = local_point_map(kfs, poses[picked], self.cfg.local_map.voxel_m)
            return
        kfs = self.keyframes[-n:]
        poses = self.graph.poses([self.trajectory.key(kf.index) for kf in kfs])
        self.local_map = self.sensor.local_map(self, kfs, poses)

    def _reusable(self, T_map_robot: F64) -> int | None:
        k = self.cfg.keyframes
        return reusable_keyframe(self.keyframe_poses(), T_map_robot, self.anchor.index,
                                 k.reuse_m, k.reuse_deg)

    # -- for the server ------------------------------------------------------------------
    def rebind(self, graph: PoseGraph) -> None:
        """Continue in ``graph`` (which now holds this robot's keys, e.g. a team's joint
        problem in the team's frame): cached map-frame poses and the local map follow."""
        self.graph = graph
        if self.keyframes:
            self.anchor.T_map_kf = graph.pose(self.trajectory.key(self.anchor.index))
            self._refresh_local_map()

    def pose_at(self, stamp_ns: int, tolerance_ns: int = 150_000_000
                ) -> tuple[int, F64] | None:
        """Where the robot was at ``stamp_ns``: a keyframe index and the robot's pose relative
        to that keyframe (``ScanPoses.at``)."""
        return self._scan_poses.at(
            stamp_ns, lambda ks: self.graph.poses([self.trajectory.key(k) for k in ks]),
            tolerance_ns)

    def sweep_due(self, stamp_ns: int) -> bool:
        """Whether the robot should stand still now for its sensor's sake: while a turning
        camera makes a whole scan (``server.slam.sweep``); never for a 360° sensor."""
        return self.sensor.stand_still(stamp_ns)

    def skip_sweep(self) -> None:
        """Drive on instead of standing still for the sensor now (``sweep_due`` asks again
        later): the stop was not worth the robot's time."""
        self.sensor.skip_stop()

    def pose_sigma(self) -> tuple[float, float, float]:
        """σ of the newest keyframe's pose (x, y [m] and θ [rad], in its own frame), from
        the graph's marginal covariance."""
        cov = self.graph.marginal_covariance(self.trajectory.key(len(self.keyframes) - 1))
        s = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return float(s[0]), float(s[1]), float(s[2])

    # -- accessors -----------------------------------------------------------------------
    @property
    def robot_char(self) -> str:
        return self.trajectory.robot_char

    @property
    def narrow(self) -> bool:
        """Whether the latest scan was a narrow sensor's (a depth camera's)."""
        return self.sensor.narrow

    @narrow.setter
    def narrow(self, narrow: bool) -> None:
        # as if the latest scan had been such a sensor's (a test's stand-in for a scan)
        self.sensor = self._sensors.narrow if narrow else self._sensors.wide

    @property
    def pose(self) -> F64:
        """Current robot pose (x, y, θ) in the map frame."""
        return self.anchor.T_map_robot

    def keyframe_pose(self, index: int) -> F64:
        """The optimised pose of one keyframe."""
        return self.graph.pose(self.trajectory.key(index))

    def keyframe_poses(self) -> F64:
        """Optimised poses (K, 3) of all keyframes, in keyframe order."""
        return self.graph.poses(self.trajectory.all_keys())

    def scan_poses(self) -> tuple[NDArray[np.int64], F64]:
        """Stamps [ns] and optimised map-frame poses (N, 3) of every scan added so far."""
        return self._scan_poses.in_map(self.keyframe_poses())

    def occupancy_grid(self) -> OccupancyGrid:
        """The occupancy grid at the current poses (incremental, or re-rendered if they moved)."""
        return self._mapper.update(self.keyframes, self.keyframe_poses())

    def point_cloud(self, voxel_m: float = 0.05) -> F64:
        """Keyframe points (N, 2) in the map frame, one per ``voxel_m`` cell."""
        return point_cloud(self.keyframes, self.keyframe_poses(), voxel_m)

    @property
    def loop_stats(self) -> LoopStats:
        """Counters of the loop-closure search (candidates, rejections by reason...)."""
        return self.loops.stats
