"""The simulator's configuration (YAML ← env ← CLI) and the scenarios it can run."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Literal, get_args

from pydantic import Field, model_validator

from schemas.config import BusConfig, ConfigModel
from schemas.tags import CameraMount, TagLayout
from schemas.textfile import UnreadableFile, read_yaml
from schemas.types import ID_PATTERN
from sim.errors import SimError

#: The scenarios that ship with the package, in its own worlds (not the dissertation's).
DEFAULT_SCENARIOS = Path(__file__).resolve().parent / "worlds" / "scenarios.yaml"
Pose = tuple[float, float, float]


class LidarConfig(ConfigModel):
    beams: int = Field(400, ge=1, le=8192, description="beams per sweep")
    fov_deg: float = Field(
        360.0, gt=0.0, le=360.0, description="field of view, centred on the robot's forward axis")
    range_min_m: float = Field(0.05, ge=0.0, description="readings closer are no-returns")
    range_max_m: float = Field(10.0, gt=0.0, le=65.0, description="readings farther are no-returns")
    sigma_m: float = Field(0.008, ge=0.0, le=1.0, description="σ of the Gaussian range noise")
    rate_hz: float = Field(
        10.0, gt=0.0, le=1000.0, description="sweeps per second; one simulation step per sweep")
    height_m: float = Field(0.2, gt=0.0, le=10.0, description="the horizontal scan plane")

    @model_validator(mode="after")
    def _limits(self) -> LidarConfig:
        if self.range_min_m >= self.range_max_m:
            raise ValueError("range_min_m must be < range_max_m")
        return self


#: what a robot senses its surroundings with: the 360° LIDAR of ``lidar``, or the depth camera
#: of ``depth`` turned on its tower (``depth``) or fixed looking forward (``depth-fixed``)
SensorKind = Literal["lidar", "depth", "depth-fixed"]
SENSOR_KINDS: tuple[str, ...] = get_args(SensorKind)


class DepthConfig(ConfigModel):
    """A depth camera's middle row as the agent's pseudo-scan makes it (defaults: a RealSense
    D435i, its depth trusted to 3 m, on a tower that turns it to four headings)."""

    beams: int = Field(
        160, ge=2, le=4096, description="beams across the field of view (pixel columns binned)")
    hfov_deg: float = Field(87.0, gt=1.0, lt=180.0, description="horizontal field of view")
    range_min_m: float = Field(0.3, ge=0.0, description="nearer readings are no-returns")
    range_max_m: float = Field(
        3.0, gt=0.0, le=20.0, description="farther readings are no-returns (depth is "
        "unreliable beyond)")
    sigma_m: float = Field(0.002, ge=0.0, le=1.0, description="σ of the depth noise at 0 m")
    sigma_per_m2: float = Field(
        0.0036, ge=0.0, le=1.0, description="σ of the depth noise grows by this × depth² "
        "[1/m]; a stereo camera's z² · subpixel / (focal length · baseline): 0.08 px / (447 px "
        "· 0.05 m) for a D435i at 848 px")
    tower_positions: int = Field(
        4, ge=1, le=64, description="headings the tower turns the camera to (equally spaced)")
    dwell_s: float = Field(0.5, ge=0.0, le=60.0, description="time at each heading")
    turn_s: float = Field(
        0.5, gt=0.0, le=60.0, description="time to turn from one heading to the next")

    @model_validator(mode="after")
    def _limits(self) -> DepthConfig:
        if self.range_min_m >= self.range_max_m:
            raise ValueError("range_min_m must be < range_max_m")
        return self


class DriveConfig(ConfigModel):
    track_width_m: float = Field(0.27, gt=0.0, description="distance between the wheels")
    radius_m: float = Field(
        0.13, gt=0.0, description="the robot's round body (collisions, other robots' LIDAR and "
        "camera)")
    v_max_mps: float = Field(0.5, gt=0.0, le=5.0, description="forward speed is clipped to this")
    omega_max_rps: float = Field(2.0, gt=0.0, le=20.0, description="turn rate is clipped to this")
    accel_max_mps2: float = Field(
        1.0, gt=0.0, description="largest change of forward speed per second")
    alpha_max_rps2: float = Field(4.0, gt=0.0, description="largest change of turn rate per second")


class OdometryConfig(ConfigModel):
    alpha1: float = Field(4e-4, ge=0.0, description="rotation noise per rotation [rad²/rad]")
    alpha2: float = Field(1e-4, ge=0.0, description="rotation noise per distance [rad²/m]")
    alpha3: float = Field(1e-4, ge=0.0, description="distance noise per distance [m²/m]")
    alpha4: float = Field(1e-5, ge=0.0, description="distance noise per rotation [m²/rad]")
    scale_sigma: float = Field(0.005, ge=0.0, le=0.5, description="σ of the distance scale")
    turn_scale_sigma: float = Field(0.01, ge=0.0, le=0.5, description="σ of the turn scale")


class CameraConfig(ConfigModel):
    enabled: bool = Field(True, description="False: no camera images (no tag sightings)")
    width: int = Field(640, ge=16, le=8192, description="image width [px]")
    height: int = Field(480, ge=16, le=8192, description="image height [px]")
    hfov_deg: float = Field(60.0, gt=1.0, lt=170.0, description="horizontal field of view")
    rate_hz: float = Field(5.0, gt=0.0, description="frames per second")
    max_range_m: float = Field(7.0, gt=0.0, description="tags farther away are not drawn")
    min_facing_cos: float = Field(0.2, ge=0.0, le=1.0,
                                  description="cos of the largest viewing angle off the tag normal")
    blur_sigma_px: float = Field(
        0.6, ge=0.0, le=10.0, description="σ of the Gaussian blur on each image")
    noise_sigma: float = Field(2.0, ge=0.0, le=50.0, description="pixel noise [grey levels]")
    spurious_rate: float = Field(0.0, ge=0.0, le=1.0, description="share of tag views drawn "
                                 "false (another robot's id, a pose ≥ 1 m or ≥ 30° off, or a "
                                 "tag behind a wall), to test merge verification")


class SimConfig(ConfigModel):
    world: str | None = Field(None, description="world file (.world/.sdf or nav2 .yaml)")
    scenario: str | None = Field(None, description="a case of scenarios_file")
    scenarios_file: str = Field(
        str(DEFAULT_SCENARIOS), description="the file the scenario is looked up in")
    model_path: list[str] = Field(
        default_factory=list, description="folders searched for Gazebo models a world includes")
    robots: dict[str, Pose] = Field(default_factory=dict, description="robot id -> spawn pose")
    sensors: dict[str, SensorKind] = Field(
        default_factory=dict, description="robot id -> its range sensor (lidar, depth, "
        "depth-fixed); robots not named have the LIDAR")
    seed: int = Field(
        0, ge=0, le=2**63 - 1, description="random seed (noise, spurious views): one seed, one "
        "run")
    lockstep: bool = Field(
        False, description="advance a step only after every agent has acknowledged the last one "
        "(deterministic); otherwise real time × real_time_factor")
    real_time_factor: float = Field(
        1.0, gt=0.0, le=1e4, description="simulated seconds per wall second, when not in lockstep")
    physics_rate_hz: float = Field(
        50.0, gt=0.0, le=10000.0, description="integration steps per second of simulated time")
    duration_s: float | None = Field(None, gt=0.0, description="stop after this sim time")
    max_steps: int | None = Field(None, ge=1, description="stop after this many steps")
    out: str | None = Field(None, description="folder for truth.jsonl and summary.json")
    lidar: LidarConfig = LidarConfig()
    depth: DepthConfig = DepthConfig()
    drive: DriveConfig = DriveConfig()
    odometry: OdometryConfig = OdometryConfig()
    camera: CameraConfig = CameraConfig()
    tags: TagLayout = TagLayout()
    camera_mount: CameraMount = CameraMount()
    bus: BusConfig = BusConfig()
    start_timeout_s: float = Field(60.0, gt=0.0, description="lockstep: wait for agents")
    ack_timeout_s: float = Field(60.0, gt=0.0, description="lockstep: give up on an ack")
    resend_after_s: float = Field(1.0, gt=0.0, description="lockstep: re-send a step")
    command_ttl_s: float = Field(
        0.5, gt=0.0, le=10.0, description="a robot whose last motor command (in lockstep: last "
        "ack) is older than this [sim s] stops until a new one arrives, as the base firmware "
        "does (it caps a command's timeout at 0.5 s)")

    @model_validator(mode="after")
    def _ids(self) -> SimConfig:
        for rid in [*self.robots, *self.sensors]:
            if not re.match(ID_PATTERN, rid):
                raise ValueError(f"robot id {rid!r} does not match {ID_PATTERN}")
        return self


def parse_robot_args(specs: list[str]) -> tuple[dict[str, Pose], dict[str, str]]:
    """Every ``--robot`` of a command line: spawn poses, and the sensors named."""
    robots: dict[str, Pose] = {}
    sensors: dict[str, str] = {}
    for spec in specs:
        rid, pose, sensor = parse_robot_arg(spec)
        if rid in robots:
            raise SimError(f"--robot {spec!r}: robot {rid} is given twice")
        robots[rid] = pose
        if sensor is not None:
            sensors[rid] = sensor
    return robots, sensors


def parse_robot_arg(spec: str) -> tuple[str, Pose, str | None]:
    """``r1:x,y[,yaw][:sensor]`` -> ("r1", (x, y, yaw), sensor or None); yaw in radians
    (default 0), sensor one of ``SENSOR_KINDS``."""
    m = re.match(r"^\s*([^:\s]+)\s*:\s*([^:]+?)\s*(?::\s*([^:\s]*)\s*)?$", spec)
    if m is None:
        raise SimError(f"--robot {spec!r}: expected ID:X,Y[,YAW][:SENSOR]")
    rid, rest, sensor = m.group(1), m.group(2), m.group(3)
    if sensor is not None and sensor not in SENSOR_KINDS:
        raise SimError(f"--robot {spec!r}: unknown sensor {sensor!r} "
                       f"(known: {', '.join(SENSOR_KINDS)})")
    if not re.match(ID_PATTERN, rid):
        raise SimError(f"--robot {spec!r}: robot id {rid!r} does not match {ID_PATTERN}")
    try:
        v = [float(t) for t in rest.split(",")]
    except ValueError:
        raise SimError(f"--robot {spec!r}: X,Y[,YAW] must be numbers") from None
    if len(v) not in (2, 3) or not all(math.isfinite(x) for x in v):
        raise SimError(f"--robot {spec!r}: expected 2 or 3 finite numbers")
    return rid, (v[0], v[1], v[2] if len(v) == 3 else 0.0), sensor


def resolve_scene_sensors(cfg: SimConfig) -> tuple[Path, dict[str, Pose], dict[str, str]]:
    """The world file, spawn poses and sensors: the scenario's, replaced by explicit ones (a
    sensor given for a robot replaces the scenario's for that robot)."""
    world: Path | None = Path(cfg.world) if cfg.world else None
    robots = dict(cfg.robots)
    sensors: dict[str, str] = {}
    if cfg.scenario:
        case = load_scenario(Path(cfg.scenarios_file), cfg.scenario)
        if world is None:
            world = Path(cfg.scenarios_file).parent / str(case["world"])
        spawn = case["robots"]
        if not robots and isinstance(spawn, dict):
            robots = {str(k): _pose(v, cfg.scenario, str(k)) for k, v in spawn.items()}
        sensors = _sensors(case.get("sensors"), cfg.scenario)
    sensors.update(cfg.sensors)
    if world is None:
        raise SimError("no world: give --world PATH or --scenario NAME")
    if not robots:
        raise SimError("no robots: give --robot ID:X,Y,YAW or a --scenario")
    if unknown := sorted(set(sensors) - set(robots)):
        raise SimError(f"a sensor is given for {', '.join(unknown)}, which is not a robot here")
    return world, robots, {rid: k for rid, k in sensors.items() if k != "lidar"}


def _sensors(v: object, scenario: str) -> dict[str, str]:
    if v is None:
        return {}
    if not isinstance(v, dict) or not all(k in SENSOR_KINDS for k in v.values()):
        raise SimError(f"scenario {scenario}: sensors must map robot ids to one of "
                       f"{', '.join(SENSOR_KINDS)}")
    return {str(k): str(s) for k, s in v.items()}


def load_scenario(path: Path, name: str) -> dict[str, object]:
    """The case ``name`` of a scenarios file; a name the file lists under ``renamed`` fails
    with its new name."""
    try:
        data = read_yaml(path, "scenarios are YAML text")
    except UnreadableFile as e:
        raise SimError(str(e)) from None
    cases = data.get("cases") if isinstance(data, dict) else None
    if not isinstance(cases, dict):
        raise SimError(f"{path}: expected a 'cases' mapping")
    case = cases.get(name)
    renamed = data.get("renamed") or {}
    if case is None and isinstance(renamed, dict) and name in renamed:
        raise SimError(f"scenario {name!r} is called {renamed[name]!r} now: mrslam's own "
                       f"building with the poses and settings of the dissertation's {name}, "
                       "not the dissertation's world (that one is in its own scenarios file)")
    if not isinstance(case, dict) or "world" not in case or not isinstance(
            case.get("robots"), dict):
        known = ", ".join(sorted(str(k) for k in cases))
        raise SimError(f"{path}: no scenario {name!r} with a world and robots (known: {known})")
    return case


def _pose(v: object, scenario: str, rid: str) -> Pose:
    if not (isinstance(v, list | tuple) and len(v) == 3):
        raise SimError(f"scenario {scenario}: robot {rid}: pose must be [x, y, yaw]")
    try:
        x, y, th = (float(a) for a in v)
    except (TypeError, ValueError):
        raise SimError(f"scenario {scenario}: robot {rid}: pose must be numbers") from None
    return x, y, th
