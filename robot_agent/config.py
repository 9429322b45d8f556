"""The agent's configuration (``mrslam agent -c agent.yaml``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from schemas.config import BusConfig, ConfigModel, Finite
from schemas.tags import CameraMount, TagLayout
from schemas.types import ID_PATTERN


class DetectorConfig(ConfigModel):
    enabled: bool = Field(True, description="False: no tag detection")
    max_reprojection_px: float = Field(
        2.0, gt=0.0, description="a marker pose whose RMS reprojection error is larger is dropped")
    range_a_m: float = Field(0.01, gt=0.0, description="σ_range = a + b r²")
    range_b_per_m: float = Field(0.01, ge=0.0, description="b of σ_range [1/m]")
    bearing_a_rad: float = Field(0.005, gt=0.0, description="σ_bearing = a + b r")
    bearing_b_rad_per_m: float = Field(0.002, ge=0.0, description="b of σ_bearing [rad/m]")
    yaw_a_rad: float = Field(0.03, gt=0.0, description="σ_yaw = a + b r²")
    yaw_b_rad_per_m2: float = Field(0.03, ge=0.0, description="b of σ_yaw [rad/m²]")
    ambiguous_ratio: float = Field(
        3.0, ge=1.0, description="when the mirrored pose solution fits within this factor of the "
        "best, the tag's heading is ambiguous")
    ambiguous_sigma_yaw_rad: float = Field(
        1.5, gt=0.0, description="σ_yaw given to an ambiguous heading")
    line_of_sight: bool = Field(True, description="drop sightings with a closer LIDAR return "
                                "toward the tag (seen through a gap in a wall)")
    los_half_width_deg: float = Field(
        3.0, gt=0.0, le=45.0, description="LIDAR beams this close to the tag's bearing are "
        "checked")
    los_margin_m: float = Field(0.4, ge=0.0, description="returns this much nearer than the "
                                "tag are not the observed robot itself")
    los_max_age_s: float = Field(0.3, gt=0.0, description="the scan must be this recent")
    lidar_fix: bool = Field(True, description="take a sighted robot's range and bearing from "
                            "the LIDAR returns off its body when they confirm the tag (past "
                            "~2 m a tag's range is biased, its centre uncertain across)")
    body_radius_m: float = Field(0.13, ge=0.0, le=2.0, description="radius of the robots' "
                                 "(round) bodies at the LIDAR's height; 0: no LIDAR fix")
    lidar_sigma_m: float = Field(0.01, gt=0.0, le=0.5, description="σ of one LIDAR range")
    lidar_fix_max_age_s: float = Field(0.05, gt=0.0, description="a sweep this close to the "
                                       "frame's time; else the next sweep is awaited")


class LockstepConfig(ConfigModel):
    """How the agent answers a lockstep simulator."""

    wait_for_command: bool = Field(
        True, description="while the server is alive, ack a step only after its command")
    command_timeout_s: float = Field(5.0, gt=0.0, description="wall-clock wait for it")
    first_command_timeout_s: float = Field(
        55.0, gt=0.0, description="wall-clock wait for the server's first command: a server "
        "starting on a busy or cold machine may take longer than command_timeout_s to "
        "answer its first scan; keep it under the simulator's ack_timeout_s")


class RplidarConfig(ConfigModel):
    """SLAMTEC RPLIDAR A-series on a serial port (standard scan mode)."""

    port: str = Field("/dev/rplidar", description="serial port (deploy/ installs this udev name)")
    baud: int = Field(115200, description="A1/A2: 115200, A3: 256000")
    beams: int = Field(360, ge=8, le=8192, description="fixed beams per sweep, from -pi")
    range_min_m: float = Field(0.15, ge=0.0, description="readings closer are no-returns")
    range_max_m: float = Field(12.0, gt=0.0, le=65.0, description="readings farther are no-returns")
    mount_yaw_rad: float = Field(0.0, ge=-7.0, le=7.0,
                                 description="yaw of the device's 0 deg mark on the robot")
    clockwise: bool = Field(True, description="device angles grow clockwise (RPLIDAR: yes)")
    motor_dtr: bool = Field(True, description="motor on/off through DTR (A2 USB adapter)")
    reconnect_s: float = Field(1.0, gt=0.0, description="retry period after the device is lost")


class MotorBaseConfig(ConfigModel):
    """Differential-drive base behind a microcontroller (protocol: deploy/firmware/README.md)."""

    port: str = Field("/dev/mrslam-base", description="serial port of the microcontroller")
    baud: int = Field(115200, description="serial baud rate")
    track_m: float = Field(0.30, gt=0.0, le=5.0, description="distance between the wheels b")
    wheel_radius_m: float = Field(0.05, gt=0.0, le=1.0, description="radius of the drive wheels")
    ticks_per_rev: float = Field(1000.0, gt=0.0, description="encoder ticks per wheel turn")
    keepalive_s: float = Field(0.05, gt=0.0, le=0.2, description="command re-send period")
    hold_s: float = Field(0.4, gt=0.0, le=0.5,
                          description="a target not renewed for this long becomes a stop")
    firmware_timeout_ms: int = Field(300, ge=50, le=500,
                                     description="the firmware stops without frames this long")
    link_timeout_s: float = Field(0.5, gt=0.0, description="no encoder frames: reconnect")
    reconnect_s: float = Field(1.0, gt=0.0, description="retry period after the link is lost")


class CameraConfig(ConfigModel):
    enabled: bool = Field(True, description="False: no camera (no tag sightings)")
    device: int | str = Field(0, description="V4L2 index or path/URL for cv2.VideoCapture")
    calibration: str | None = Field(None, description="YAML/JSON with K and dist")
    rate_hz: float = Field(5.0, gt=0.0, le=60.0, description="frames handed to the detector")
    width: int | None = Field(
        None, gt=0, description="capture width [px]; null: the calibration's or the device's")
    height: int | None = Field(
        None, gt=0, description="capture height [px]; null: the calibration's or the device's")


class TowerConfig(ConfigModel):
    """A depth camera (RealSense, through the optional pyrealsense2 package) turned by a
    stepper on a tower, homed on an optical trigger: one 360° pseudo-scan per turn
    (protocol: robot_agent/drivers/tower_protocol.py)."""

    port: str = Field("/dev/mrslam-tower", description="serial port of the stepper controller")
    baud: int = Field(115200, description="serial baud rate")
    steps_per_rev: int = Field(6400, ge=4, description="microsteps per turn of the tower "
                               "(motor full steps × microstepping × gear ratio)")
    zero_offset_steps: int = Field(
        0, description="microsteps from the trigger's edge to the camera looking along the "
        "robot's x axis")
    headings_deg: list[float] = Field(
        [0.0, 90.0, 180.0, 270.0], min_length=1, description="camera headings of a sweep")
    settle_s: float = Field(0.15, ge=0.0, le=5.0, description="wait after each move")
    beams: int = Field(360, ge=8, le=8192, description="fixed beams of the pseudo-scan")
    range_min_m: float = Field(0.2, ge=0.0, description="nearer depths are no-returns")
    range_max_m: float = Field(3.0, gt=0.0, le=20.0,
                               description="farther depths are no-returns (unreliable)")
    rows: int = Field(1, ge=1, le=64, description="image rows around the middle, nearest wins")
    reconnect_s: float = Field(1.0, gt=0.0, description="retry period after the tower is lost")
    camera_width: int = Field(848, gt=0, description="depth stream width [px]")
    camera_height: int = Field(480, gt=0, description="depth stream height [px]")
    camera_fps: int = Field(30, gt=0, le=300, description="depth stream rate")
    camera_serial: str | None = Field(None, description="the camera's serial number (null: any)")


class HardwareConfig(ConfigModel):
    range_sensor: Literal["lidar", "depth-tower"] = Field(
        "lidar", description="lidar: the RPLIDAR of hardware.lidar; depth-tower: the depth "
        "camera on the turning tower of hardware.tower")
    lidar: RplidarConfig = RplidarConfig()
    tower: TowerConfig = TowerConfig()
    base: MotorBaseConfig = MotorBaseConfig()
    camera: CameraConfig = CameraConfig()


class AgentConfig(ConfigModel):
    robot_id: str = Field(
        "r1", pattern=ID_PATTERN, description="this robot's id (r1, r2, ...): its keys, its tag "
        "ids")
    bus: BusConfig = BusConfig()
    backend: Literal["sim", "hardware"] = Field(
        "sim", description="sim: the simulator's sensors and motors over the bus; hardware: the "
        "drivers in hardware (LIDAR, motor base, camera)")
    hardware: HardwareConfig = HardwareConfig()
    status_period_s: float = Field(1.0, gt=0.0, description="a RobotStatus is published this often")
    v_max_mps: float = Field(0.5, gt=0.0, le=5.0, description="commands are clipped to this")
    omega_max_rps: float = Field(2.0, gt=0.0, le=20.0, description="turn rates are clipped to this")
    stop_on_server_loss: bool = Field(
        True, description="stop the motors when the server's liveliness token disappears")
    command_max_age_s: float = Field(10.0, gt=0.0, description="commands stamped longer ago "
                                     "on the robot's clock are ignored (a replay, a stamp-0 "
                                     "stranger); the server stamps each with its scan's time")
    command_max_ahead_s: float = Field(1.0, ge=0.0, description="commands stamped this far "
                                       "ahead of the robot's clock are ignored")
    max_queued_frames: int = Field(4, ge=1, description="older frames are dropped beyond this")
    tags: TagLayout = TagLayout()
    camera_mount: CameraMount = CameraMount()
    detector: DetectorConfig = DetectorConfig()
    lockstep: LockstepConfig = LockstepConfig()
    sim_clock_steps: list[tuple[Finite, Finite]] = Field(
        default_factory=list, description="simulation only: (at [s] of sim time, step [s]): "
        "from then on the robot's own clock, which stamps what it sends, is off by the step "
        "(to try the server with clocks that NTP corrects or that boot in 1970)")
    sim_odometry_at_zero: bool = Field(
        False, description="simulation only: odometry starts at zero where the agent first "
        "hears of its robot, as a real robot's wheel odometry does when it boots (the demo "
        "sets it for an agent it reboots mid-run); false: the simulator's odometry, which "
        "starts at the robot's spawn pose")
