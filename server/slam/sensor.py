"""The seam between ``RobotSlam``'s pipeline and what one kind of range sensor needs of it.

``RobotSlam.add_scan`` is the same for every sensor: predict, match the local map, keyframe,
optimise, close loops, map. What differs is behind ``SensorModel``, as a nav2 planner is
behind its interface: how ranges become points, how a scan is matched, what the model makes
of the match (``place``), when a scan shows enough that is new to be a keyframe, what factors
a keyframe adds besides the pipeline's, what the local map is drawn from, and when the robot
must stand still for the sensor.

Two models: ``LidarSensor`` here, the 360° LIDAR's and the default, which adds nothing to the
pipeline; and ``NarrowSensor`` (``server.slam.narrow``), a depth camera's narrow views. A
robot's scans say which it has: a scan whose beams span less than ``matcher.narrow_fov_deg``
goes to the narrow model (``SensorChoice``), so the server need not be told, and a robot's
log replays the same with any configuration of the fleet.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from server.slam.config import ScanConfig, SlamConfig
from server.slam.frontend import FrontendMatch, icp_params, match_step
from server.slam.heading_ties import HeadingTies
from server.slam.icp import PointMap
from server.slam.keyframes import Keyframe, local_point_map
from server.slam.scan import ScanPoints, field_of_view, scan_to_points
from server.slam.view import Placement, SlamView

F64 = NDArray[np.float64]


class SensorModel(Protocol):
    """How one kind of sensor's scans go through ``RobotSlam``'s pipeline (see the module).

    ``narrow`` tells the parts outside the pipeline (the loop closer's search window, the
    steering's obstacle memory) that the sensor sees little at a time; ``local_keyframes`` is
    how many of the latest keyframes the local map is drawn from."""

    narrow: bool
    local_keyframes: int

    def prepare(self, ranges_m: F64, angles_rad: F64, free_m: float) -> ScanPoints:
        """Points and normals (sensor frame) of one scan; beams without a return mark free
        space up to ``free_m`` (0: nothing)."""
        ...

    def match(self, scan: ScanPoints, local_map: PointMap, T_pred: F64, T_last: F64,
              T_step_velocity: F64, T_step_odom: F64) -> FrontendMatch:
        """The scan's pose in the map frame, matched against the local map from the
        odometry's prediction ``T_pred``."""
        ...

    def place(self, slam: SlamView, scan: ScanPoints, match: FrontendMatch, T_odom_robot: F64,
              T_pred: F64, T_last: F64, T_step_odom: F64) -> Placement:
        """What the model makes of the scan and its match before the keyframe step."""
        ...

    def sees_new(self, scan: ScanPoints, T_map_robot: F64, local_map: PointMap) -> bool:
        """Whether the scan should be a keyframe for what it shows that the local map has
        not, though the robot moved too little for one."""
        ...

    def on_keyframe(self, slam: SlamView, k: int, placed: Placement, T_odom_robot: F64
                    ) -> None:
        """Keyframe ``k`` was just added from ``placed``: the model's own factors."""
        ...

    def local_map(self, slam: SlamView, keyframes: Sequence[Keyframe], T_map_kf: F64
                  ) -> PointMap:
        """The map the next scans are matched against, from ``keyframes`` at ``T_map_kf``."""
        ...

    def stand_still(self, stamp_ns: int) -> bool:
        """Whether the robot should stand still now for the sensor's sake."""
        ...

    def skip_stop(self) -> None:
        """The robot drives on instead of standing still now (the stop was not worth its
        time); the model asks again later."""
        ...


def scan_points(ranges_m: F64, angles_rad: F64, cfg: ScanConfig, normal_window: int,
                free_m: float) -> ScanPoints:
    """``scan_to_points`` with the settings of ``slam.scan`` and a sensor's normal window."""
    return scan_to_points(ranges_m, angles_rad, cfg.min_range_m, cfg.max_range_m, normal_window,
                          cfg.normal_max_gap_m, cfg.min_point_spacing_m, free_m)


class LidarSensor:
    """A 360° LIDAR's scans: the pipeline as it is, nothing added (square walls only with
    ``square_walls.narrow_only`` off: a 360° scan holds its own heading)."""

    narrow = False

    def __init__(self, cfg: SlamConfig, ties: HeadingTies | None = None) -> None:
        self.cfg = cfg
        self.icp = icp_params(cfg.matcher)
        self.ties = ties
        self.local_keyframes = cfg.local_map.keyframes

    def prepare(self, ranges_m: F64, angles_rad: F64, free_m: float) -> ScanPoints:
        return scan_points(ranges_m, angles_rad, self.cfg.scan, self.cfg.scan.normal_window,
                           free_m)

    def match(self, scan: ScanPoints, local_map: PointMap, T_pred: F64, T_last: F64,
              T_step_velocity: F64, T_step_odom: F64) -> FrontendMatch:
        return match_step(scan, local_map, T_pred, T_last, T_step_velocity, T_step_odom,
                          self.cfg.matcher, self.icp)

    def place(self, slam: SlamView, scan: ScanPoints, match: FrontendMatch, T_odom_robot: F64,
              T_pred: F64, T_last: F64, T_step_odom: F64) -> Placement:
        return Placement(scan, match)

    def sees_new(self, scan: ScanPoints, T_map_robot: F64, local_map: PointMap) -> bool:
        return False

    def on_keyframe(self, slam: SlamView, k: int, placed: Placement, T_odom_robot: F64
                    ) -> None:
        if self.ties is not None and self.ties.tie(slam.graph, slam.trajectory, k,
                                                   placed.scan.normals,
                                                   placed.match.T_map_robot):
            slam.stats.heading_ties += 1

    def local_map(self, slam: SlamView, keyframes: Sequence[Keyframe], T_map_kf: F64
                  ) -> PointMap:
        return local_point_map(keyframes, T_map_kf, self.cfg.local_map.voxel_m)

    def stand_still(self, stamp_ns: int) -> bool:
        return False

    def skip_stop(self) -> None:
        return None


@dataclass
class SensorChoice:
    """A robot's two sensor models, built once from its configuration; each scan goes to the
    one its field of view calls for (``matcher.narrow_fov_deg``)."""

    wide: SensorModel
    narrow: SensorModel
    narrow_fov_deg: float

    def for_angles(self, angles_rad: F64) -> SensorModel:
        """The model for a scan whose beams point at ``angles_rad``."""
        narrow = field_of_view(angles_rad)[0] < math.radians(self.narrow_fov_deg)
        return self.narrow if narrow else self.wide
