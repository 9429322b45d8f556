"""The hardware backend: an RPLIDAR (or a depth camera on a turning tower), a motor base behind
a microcontroller, a camera.

Every driver runs its own thread and reconnects on its own, so the agent keeps running (and
reports itself degraded) while a cable is out. The robot's clock is the host's wall clock
(``time.time_ns``, kept by NTP), which stamps sweeps, odometry and frames alike.
"""

from __future__ import annotations

import time

from robot_agent.backend import Backend, Base, Pose
from robot_agent.config import HardwareConfig, TowerConfig
from robot_agent.drivers.base import SerialBase
from robot_agent.drivers.camera import CalibrationError, OpenCVCamera, load_calibration
from robot_agent.drivers.realsense import RealSenseDepth
from robot_agent.drivers.rplidar import RplidarSource
from robot_agent.drivers.tower import DepthCamera, Tower, TowerSource


def hardware_backend(cfg: HardwareConfig) -> Backend:
    lc, bc, cc = cfg.lidar, cfg.base, cfg.camera
    camera = None
    if cc.enabled:
        if cc.calibration is None:
            raise CalibrationError("hardware.camera.calibration is required when the camera "
                                   "is enabled (a YAML/JSON file with K and dist)")
        camera = OpenCVCamera(cc.device, load_calibration(cc.calibration), cc.rate_hz,
                              cc.width, cc.height)
    base = SerialBase(bc.port, bc.track_m, bc.wheel_radius_m, bc.ticks_per_rev, bc.baud,
                      bc.keepalive_s, bc.hold_s, bc.firmware_timeout_ms, bc.link_timeout_s,
                      bc.reconnect_s)
    base.start()
    lidar: RplidarSource | TowerSource
    if cfg.range_sensor == "depth-tower":
        lidar = depth_tower(cfg.tower, base)
    else:
        lidar = RplidarSource(lc.port, lc.baud, lc.beams, round(lc.range_min_m * 1000),
                              round(lc.range_max_m * 1000), lc.mount_yaw_rad, lc.clockwise,
                              lc.motor_dtr, lc.reconnect_s)

    def close() -> None:
        lidar.close()
        if camera is not None:
            camera.close()
        base.close()          # last: its final frame stops the motors

    def counters() -> dict[str, int]:
        """Problems only (connects and frame counts are not errors)."""
        out: dict[str, int] = {}
        ranging = lidar.all_counters() if isinstance(lidar, TowerSource) else lidar.counters
        for name, c in (("lidar", ranging), ("base", base.counters),
                        ("camera", camera.counters if camera is not None else {})):
            for k, v in c.items():
                if k not in ("connects", "sweeps", "frames", "hold_expired",
                             "motor_control_unsupported"):
                    out[f"{name}_{k}"] = v
        return out

    return Backend(lidar=lidar, base=base, camera=camera, now_ns=time.time_ns, close=close,
                   counters=counters)


def depth_tower(tc: TowerConfig, base: Base, frames: DepthCamera | None = None) -> TowerSource:
    """The tower of ``tc`` with its depth camera (``frames``; a RealSense by default), the
    views placed by ``base``'s odometry at each frame's capture time."""
    cam: DepthCamera = frames or RealSenseDepth(tc.camera_width, tc.camera_height, tc.camera_fps,
                                   tc.camera_serial)

    def odometry_at(stamp_ns: int) -> Pose | None:
        o = base.odometry_at(stamp_ns)
        return None if o is None else o.pose

    tower = Tower(tc.port, cam.grab, odometry_at, fx=float("nan"), cx=float("nan"),
                  steps_per_rev=tc.steps_per_rev, headings_deg=tc.headings_deg,
                  zero_offset_steps=tc.zero_offset_steps, settle_s=tc.settle_s, baud=tc.baud,
                  beams=tc.beams, max_range_m=tc.range_max_m, min_range_m=tc.range_min_m,
                  rows=tc.rows)

    def open_camera() -> None:
        cam.open()
        tower.fx, tower.cx = cam.fx, cam.cx      # the stream's intrinsics, known once open

    return TowerSource(tower, tc.reconnect_s, open_camera, cam.close)
