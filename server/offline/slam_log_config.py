"""Configuration of ``mrslam slam-log``: how a recording is read, and the SLAM it is fed to."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from schemas.config import ConfigModel, Finite
from server.offline.logs.scan_odometry import ScanOdometryParams
from server.slam.config import SlamConfig


class OdometryLimitsConfig(ConfigModel):
    """What a robot's odometry can do between two samples: a sample beyond it that the
    samples after it do not continue from is corrupt (``server.offline.logs.odomcheck``; bags)."""

    max_speed_m_s: Finite = Field(5.0, gt=0, description="fastest the robot drives [m/s]")
    max_turn_rate_deg_s: Finite = Field(360.0, gt=0, description="fastest it turns [°/s]")
    slack_m: Finite = Field(0.1, ge=0, description="allowed beyond the speed per sample [m] "
                            "(stamps jitter)")
    slack_deg: Finite = Field(10.0, ge=0, description="allowed beyond the turn rate per "
                              "sample [°]")
    max_abs_m: Finite = Field(2.0e7, gt=0, description="a position farther from the odometry's "
                              "origin is absurd (no two places on Earth are farther apart)")
    window: int = Field(5, ge=1, description="samples after a jump that decide whether it is "
                        "a spike (skipped) or where the odometry goes on from (kept)")


class ScanOdometryConfig(ConfigModel):
    """Odometry from the scans, for a recording without any
    (``server.offline.logs.scan_odometry``)."""

    key_distance_m: Finite = Field(0.1, gt=0, description="a new key scan to match against "
                                   "after moving this far")
    key_angle_deg: Finite = Field(10.0, gt=0, description="... or turning this much")

    def params(self) -> ScanOdometryParams:
        return ScanOdometryParams(self.key_distance_m, self.key_angle_deg)


class SlamLogConfig(ConfigModel):
    laser: Literal["front", "rear"] = Field("front", description="a CARMEN log's laser")
    odometry: Literal["auto", "laser", "odom", "scans"] = Field(
        "auto", description="a CARMEN log's odometry: the pose in each laser line (laser), the "
        "ODOM lines (odom), auto: the laser lines' unless missing or stale; a bag's own "
        "odometry for any of these; scans: odometry from scan matching, ignoring the "
        "recording's (what a recording without odometry gets)")
    echo: Literal["first", "last"] = Field(
        "first", description="the echo of a MultiEchoLaserScan beam used")
    laser_pose: tuple[Finite, Finite, Finite] | None = Field(
        None, description="the laser's pose (x [m], y [m], yaw [rad]) on the robot, the frame "
        "of the bag's odometry; replaces /tf_static (default: /tf_static, else the origin)")
    stamp_jitter_fraction: Finite = Field(
        0.5, ge=0, le=1, description="a scan stamped less than this share of the scan period "
        "before the one above it is jitter: kept in file order")
    odometry_limits: OdometryLimitsConfig = OdometryLimitsConfig()
    scan_odometry: ScanOdometryConfig = ScanOdometryConfig()
    write_maps: bool = True
    slam: SlamConfig = SlamConfig()
