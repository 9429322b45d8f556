"""Which laser stream of a log to use, and the odometry pose of each of its scans."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.se2 import wrap_angle
from server.offline.logs.records import F64, CarmenError, CarmenLog, LaserRecord, OdometryRecord

FRONT_KINDS = ("ROBOTLASER1", "FLASER", "RAWLASER1", "LASER1")
REAR_KINDS = ("ROBOTLASER2", "RLASER", "RAWLASER2", "LASER2")


@dataclass(frozen=True, slots=True)
class OdometryScan:
    """A laser scan with the odometry pose of the laser (odometry frame) at its stamp."""

    record: LaserRecord
    T_odom_laser: F64


def select_stream(log_: CarmenLog, laser: str = "front") -> list[LaserRecord]:
    """The scans of one laser: the first kind present of ``FRONT_KINDS`` (or ``REAR_KINDS``).

    Newer logs write the same scan in several formats (e.g. ROBOTLASER1 and RAWLASER1); taking
    one kind avoids using a scan twice. The richest format comes first.
    """
    kinds = FRONT_KINDS if laser == "front" else REAR_KINDS
    present = log_.laser_kinds()
    for kind in kinds:
        if present[kind]:
            return [r for r in log_.lasers if r.kind == kind]
    raise CarmenError(f"no {laser} laser scans in the log (found: {dict(present)})")


def interpolate_pose(stamps: F64, poses: F64, t: float) -> F64:
    """Odometry pose at time t: linear in x, y and along the shortest arc in θ; clamped to the
    first/last pose outside the recorded span."""
    j = int(np.searchsorted(stamps, t))
    if j <= 0 or j >= len(stamps):
        return poses[min(max(j, 0), len(stamps) - 1)]
    t0, t1 = stamps[j - 1], stamps[j]
    a = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
    p0, p1 = poses[j - 1], poses[j]
    d_theta = wrap_angle(p1[2] - p0[2])
    return np.array([p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]),
                     wrap_angle(p0[2] + a * d_theta)])


def laser_poses_are_stale(scans: list[LaserRecord], stamps: F64, poses: F64) -> bool:
    """True if most laser lines carry a verbatim copy of the last ODOM pose before them.

    Some loggers write the latest odometry into the laser line instead of the odometry at the
    scan's time; at walking speed that pose lags by up to one odometry period (several cm).
    """
    with_pose = [r for r in scans if r.robot_pose is not None]
    if not with_pose or len(stamps) == 0:
        return False
    copies = 0
    for r in with_pose:
        j = int(np.searchsorted(stamps, r.stamp_s, side="right")) - 1
        if j >= 0 and r.robot_pose is not None and np.array_equal(poses[j], r.robot_pose):
            copies += 1
    return copies > 0.5 * len(with_pose)


def _odometry_table(odometry: list[OdometryRecord]) -> tuple[F64, F64]:
    stamps = np.array([o.stamp_s for o in odometry], dtype=np.float64)
    poses = np.array([o.pose for o in odometry], dtype=np.float64).reshape(-1, 3)
    order = np.argsort(stamps, kind="stable")
    return stamps[order], poses[order]


def choose_odometry_source(scans: list[LaserRecord], odometry: list[OdometryRecord],
                           requested: str = "auto") -> str:
    """``"laser"`` (the pose written in each laser line) or ``"odom"`` (``ODOM`` lines
    interpolated at the scan stamp). ``"auto"`` takes the laser lines' poses unless they are
    missing or stale copies of the last ``ODOM`` line."""
    if requested in ("laser", "odom"):
        return requested
    if requested != "auto":
        raise ValueError(f"unknown odometry source {requested!r}")
    stamps, poses = _odometry_table(odometry)
    if len(stamps) and (any(r.laser_pose is None for r in scans)
                        or laser_poses_are_stale(scans, stamps, poses)):
        return "odom"
    return "laser"


def attach_odometry(scans: list[LaserRecord], odometry: list[OdometryRecord],
                    laser_offset_x_m: float = 0.0, source: str = "auto") -> list[OdometryScan]:
    """Odometry pose of the laser for each scan.

    ``source="laser"`` takes the laser pose written in the laser line; ``"odom"`` interpolates
    the ``ODOM`` poses at the scan stamp and places the laser ``laser_offset_x_m`` ahead of the
    robot; ``"auto"``: see ``choose_odometry_source``. A scan without a pose in its line always
    takes the interpolated odometry.
    """
    stamps, poses = _odometry_table(odometry)
    use_odom = choose_odometry_source(scans, odometry, source) == "odom"
    out: list[OdometryScan] = []
    for rec in scans:
        if rec.laser_pose is not None and not use_odom:
            out.append(OdometryScan(rec, rec.laser_pose))
            continue
        if len(stamps) == 0:
            raise CarmenError("laser lines carry no pose and the log has no ODOM lines")
        robot = interpolate_pose(stamps, poses, rec.stamp_s)
        c, s = math.cos(robot[2]), math.sin(robot[2])
        laser = np.array([robot[0] + c * laser_offset_x_m, robot[1] + s * laser_offset_x_m,
                          robot[2]])
        out.append(OdometryScan(rec, laser))
    return out
