"""The hardware backend: an RPLIDAR, a motor base behind a microcontroller, a camera.

Every driver runs its own thread and reconnects on its own, so the agent keeps running (and
reports itself degraded) while a cable is out. The robot's clock is the host's wall clock
(``time.time_ns``, kept by NTP), which stamps sweeps, odometry and frames alike.
"""

from __future__ import annotations

import time

from robot_agent.backend import Backend
from robot_agent.config import HardwareConfig
from robot_agent.drivers.base import SerialBase
from robot_agent.drivers.camera import CalibrationError, OpenCVCamera, load_calibration
from robot_agent.drivers.rplidar import RplidarSource


def hardware_backend(cfg: HardwareConfig) -> Backend:
    lc, bc, cc = cfg.lidar, cfg.base, cfg.camera
    camera = None
    if cc.enabled:
        if cc.calibration is None:
            raise CalibrationError("hardware.camera.calibration is required when the camera "
                                   "is enabled (a YAML/JSON file with K and dist)")
        camera = OpenCVCamera(cc.device, load_calibration(cc.calibration), cc.rate_hz,
                              cc.width, cc.height)
    lidar = RplidarSource(lc.port, lc.baud, lc.beams, round(lc.range_min_m * 1000),
                          round(lc.range_max_m * 1000), lc.mount_yaw_rad, lc.clockwise,
                          lc.motor_dtr, lc.reconnect_s)
    base = SerialBase(bc.port, bc.track_m, bc.wheel_radius_m, bc.ticks_per_rev, bc.baud,
                      bc.keepalive_s, bc.hold_s, bc.firmware_timeout_ms, bc.link_timeout_s,
                      bc.reconnect_s)
    base.start()

    def close() -> None:
        lidar.close()
        if camera is not None:
            camera.close()
        base.close()          # last: its final frame stops the motors

    def counters() -> dict[str, int]:
        """Problems only (connects and frame counts are not errors)."""
        out: dict[str, int] = {}
        for name, c in (("lidar", lidar.counters), ("base", base.counters),
                        ("camera", camera.counters if camera is not None else {})):
            for k, v in c.items():
                if k not in ("connects", "sweeps", "frames", "hold_expired",
                             "motor_control_unsupported"):
                    out[f"{name}_{k}"] = v
        return out

    return Backend(lidar=lidar, base=base, camera=camera, now_ns=time.time_ns, close=close,
                   counters=counters)
