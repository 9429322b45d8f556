"""The simulation itself, free of I/O: robots in a world, stepped at the LIDAR rate.

One step is one LIDAR period. ``sense()`` returns what every robot perceives at the current
time (scan, wheel odometry, camera frames when another robot's tag is in view) plus the ground
truth; ``advance()`` applies the latest commands and integrates the physics to the next step in
``substeps`` equal parts. A robot whose disc would touch a wall or another robot does not move
on that substep, stops, and has a collision counted (once per contact: pushing on against the
wall is the same collision until the robot has backed off by ``CONTACT_MARGIN_M``).

A command holds for ``command_ttl_ns`` of simulated time from the moment it was given (as the
motor board's firmware holds a speed only for its timeout): a robot whose command is older
stops until a newer one arrives, and the lapse is counted and logged once.

Randomness comes only from numpy Generators seeded from (seed, robot id), one stream each for
LIDAR noise, odometry and camera noise, so a robot's noise does not depend on which other robots
exist or on what the camera renders; nothing reads the wall clock.
"""

from __future__ import annotations

import logging
import math
import zlib
from dataclasses import dataclass, field

import numpy as np

from schemas.se2 import wrap_angle
from schemas.tags import CameraMount, TagLayout
from sim.camera import PinholeCamera, TagRenderer, TagView, visible_tags
from sim.errors import SimError
from sim.geometry import between2
from sim.odometry import OdometryNoise
from sim.raycast import RayCaster, line_of_sight
from sim.robot import (
    DriveLimits,
    Obstacles,
    arc_step,
    collisions,
    limit_command,
    point_in_polygons,
)
from sim.world import World

log = logging.getLogger(__name__)
Pose = tuple[float, float, float]
#: A robot in contact counts a new collision only after getting this far from the obstacle.
CONTACT_MARGIN_M = 0.02


@dataclass(frozen=True)
class TowerSpec:
    """A sensor turned in steps on a tower (Omni's depth camera): it rests ``dwell_ns`` at
    each of ``positions`` headings (0, 360°/positions, ...) and takes ``turn_ns`` to turn to
    the next one, round and round, from heading 0 at simulation time 0."""

    positions: int = 4
    dwell_ns: int = 500_000_000
    turn_ns: int = 500_000_000

    def yaw_at(self, t_ns: int) -> float:
        """The sensor's heading in the robot frame at ``t_ns`` (turning at a constant rate)."""
        period = self.dwell_ns + self.turn_ns
        k, into = divmod(t_ns % (period * self.positions), period)
        step = 2 * math.pi / self.positions
        turned = 0.0 if into < self.dwell_ns else (into - self.dwell_ns) / max(self.turn_ns, 1)
        return wrap_angle((k + turned) * step)


@dataclass(frozen=True)
class LidarSpec:
    """A range sensor: a 360° LIDAR (the default), or a depth camera's middle row as the
    agent's pseudo-scan makes it (``depth``: the noise is on the depth along the optical axis
    and grows with its square, as a stereo camera's does; beams past ``range_max_m`` are
    no-returns). A sensor narrower than 360° looks along the robot's heading, or along its
    ``tower``'s."""

    beams: int = 400
    fov_rad: float = 2 * math.pi
    range_min_m: float = 0.05
    range_max_m: float = 10.0
    sigma_m: float = 0.008
    #: added σ per square metre of range (depth: of depth along the optical axis)
    sigma_per_m2: float = 0.0
    depth: bool = False
    tower: TowerSpec | None = None

    @property
    def full(self) -> bool:
        return self.fov_rad >= 2 * math.pi - 1e-9

    @property
    def angle_min_rad(self) -> float:
        return -math.pi if self.full else -self.fov_rad / 2

    @property
    def angle_increment_rad(self) -> float:
        return self.fov_rad / (self.beams if self.full else max(self.beams - 1, 1))

    def heading_at(self, t_ns: int) -> float:
        """Where the middle of the field of view looks at ``t_ns``, in the robot frame."""
        return 0.0 if self.tower is None or self.full else self.tower.yaw_at(t_ns)

    def angle_min_at(self, t_ns: int) -> float:
        heading = self.heading_at(t_ns)
        return self.angle_min_rad if heading == 0.0 else wrap_angle(self.angle_min_rad + heading)

    def noisy(self, true: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Readings of the true ranges (one per beam, from ``angle_min_rad``): Gaussian noise
        growing with range, no-returns (inf) outside the limits."""
        z = rng.standard_normal(len(true))
        if self.depth:
            alpha = self.angle_min_rad + self.angle_increment_rad * np.arange(len(true))
            c = np.cos(alpha)
            along = true * c
            with np.errstate(invalid="ignore"):
                out = (along + (self.sigma_m + self.sigma_per_m2 * along ** 2) * z) / c
        else:
            with np.errstate(invalid="ignore"):
                out = true + (self.sigma_m + self.sigma_per_m2 * true ** 2) * z
        out[~np.isfinite(out) | (out > self.range_max_m) | (out < self.range_min_m)] = np.inf
        return out

    @property
    def cast_range_m(self) -> float:
        """How far rays must be cast for every reading that can come out within range."""
        far = self.range_max_m + 4 * (self.sigma_m + self.sigma_per_m2 * self.range_max_m ** 2)
        return far / (math.cos(min(self.fov_rad / 2, 1.4)) if self.depth else 1.0)


@dataclass(frozen=True)
class BeamGeometry:
    """Where one robot's sweep of a step looks: beam ``i`` at ``angle_min_rad + i * inc``."""

    angle_min_rad: float
    angle_increment_rad: float
    range_min_m: float
    range_max_m: float


@dataclass(frozen=True)
class CameraSpec:
    camera: PinholeCamera = field(default_factory=PinholeCamera)
    every_steps: int = 2            # render on steps divisible by this (0: no camera)
    max_range_m: float = 7.0
    min_facing_cos: float = 0.2
    blur_sigma_px: float = 0.6
    noise_sigma: float = 2.0
    spurious_rate: float = 0.0      # share of views drawn false (see ``Simulator._falsify``)


@dataclass(frozen=True)
class SimParams:
    step_ns: int = 100_000_000
    substeps: int = 5
    lidar: LidarSpec = field(default_factory=LidarSpec)
    drive: DriveLimits = field(default_factory=DriveLimits)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    camera: CameraSpec = field(default_factory=CameraSpec)
    tags: TagLayout = field(default_factory=TagLayout)
    mount: CameraMount = field(default_factory=CameraMount)
    command_ttl_ns: int | None = None   # None: a command holds until the next one
    #: robots whose range sensor is not ``lidar`` (e.g. a depth camera)
    sensors: dict[str, LidarSpec] = field(default_factory=dict)

    def sensor(self, robot_id: str) -> LidarSpec:
        return self.sensors.get(robot_id, self.lidar)


@dataclass
class RobotState:
    robot_id: str
    pose: Pose
    odom: Pose
    bias: tuple[float, float]
    rng_lidar: np.random.Generator
    rng_odom: np.random.Generator
    rng_camera: np.random.Generator
    v: float = 0.0
    w: float = 0.0
    cmd: tuple[float, float] = (0.0, 0.0)
    cmd_stamp_ns: int = 0          # simulation time the command was given
    cmd_expired: bool = False      # its time-to-live ran out: the robot is held still
    commands_expired: int = 0      # lapses of a moving command
    collisions: int = 0
    in_contact: bool = False
    distance_m: float = 0.0
    image_seq: int = 0
    teleports: int = 0             # moved by hand (``Simulator.teleport``)


@dataclass(frozen=True)
class Frame:
    """A rendered camera frame and what it shows."""

    image: np.ndarray                        # (H, W) uint8
    seq: int
    views: list[TagView]
    relatives: list[tuple[str, int, Pose]]   # (observed id, tag id, observed pose in observer)
    spurious: dict[int, str] = field(default_factory=dict)  # tag id -> how it was falsified


@dataclass(frozen=True)
class Observation:
    step: int
    stamp_ns: int
    ranges_m: dict[str, np.ndarray]          # inf = no return
    odometry: dict[str, tuple[Pose, float, float]]  # (pose, v, ω)
    frames: dict[str, Frame]
    truth: dict[str, RobotState]
    #: where each robot's sweep looked (a turned or narrow sensor's moves with time)
    beams: dict[str, BeamGeometry] = field(default_factory=dict)


def robot_seed(seed: int, robot_id: str) -> np.random.SeedSequence:
    return np.random.SeedSequence([seed & (2**63 - 1), zlib.crc32(robot_id.encode())])


class Simulator:
    def __init__(self, world: World, spawn: dict[str, Pose], params: SimParams,
                 seed: int = 0) -> None:
        self.world = world
        self.p = params
        self.step = 0
        self.caster = RayCaster(world.segments, world.circles)
        self.obstacles = Obstacles(world.segments, world.circles)
        self.renderer = TagRenderer(params.tags, params.camera.camera)
        self.robots: dict[str, RobotState] = {}
        for rid, pose in spawn.items():
            params.tags.tag_id(rid, "front")  # every robot needs tag ids
            lidar, odom, cam = (np.random.Generator(np.random.PCG64(s))
                                for s in robot_seed(seed, rid).spawn(3))
            bias = params.odometry.draw_bias(odom)
            p = (float(pose[0]), float(pose[1]), wrap_angle(float(pose[2])))
            self.robots[rid] = RobotState(rid, p, p, bias, lidar, odom, cam)
        self._check_spawn()

    @property
    def stamp_ns(self) -> int:
        return self.step * self.p.step_ns

    def _centres(self) -> np.ndarray:
        return np.array([r.pose[:2] for r in self.robots.values()]).reshape(-1, 2)

    def _check_spawn(self) -> None:
        c = self._centres()
        bad = collisions(c, self.p.drive.radius_m, self.world.segments, self.world.circles)
        bad |= point_in_polygons(c, self.world.polygons)
        if bad.any():
            names = [rid for rid, b in zip(self.robots, bad, strict=True) if b]
            raise SimError(f"robots {', '.join(names)} spawn inside or touching an obstacle "
                           f"of {self.world.name} (or each other)")

    def teleport(self, robot_id: str, pose: Pose) -> None:
        """Move a robot by hand: from now on it is at ``pose``, standing, and its odometry
        goes on as if nothing happened (a robot carried elsewhere, or knocked away). Raises
        ``SimError`` for a pose inside or touching an obstacle or another robot."""
        r = self.robots.get(robot_id)
        if r is None:
            raise KeyError(robot_id)
        p = (float(pose[0]), float(pose[1]), wrap_angle(float(pose[2])))
        if not all(math.isfinite(v) for v in p):
            raise SimError(f"{robot_id}: cannot be moved to {pose}: not a finite pose")
        others = np.array([o.pose[:2] for o in self.robots.values() if o is not r])
        c = np.array([p[:2]])
        bad = collisions(c, self.p.drive.radius_m, self.world.segments, self.world.circles)
        bad |= point_in_polygons(c, self.world.polygons)
        near = bool(len(others)) and bool(
            (np.hypot(*(others - c).T) < 2 * self.p.drive.radius_m).any())
        if bad.any() or near:
            raise SimError(f"{robot_id}: cannot be moved to ({p[0]:.2f}, {p[1]:.2f}): inside "
                           f"or touching an obstacle of {self.world.name} or another robot")
        r.pose, r.v, r.w, r.in_contact = p, 0.0, 0.0, False
        r.teleports += 1
        log.info("%s moved by hand to (%.2f, %.2f, %.2f)", robot_id, *p)

    def set_command(self, robot_id: str, v_mps: float, omega_rps: float,
                    stamp_ns: int | None = None) -> None:
        """The robot's command from ``stamp_ns`` (the simulation time it was given; default
        now) until the next one or until its time-to-live runs out."""
        r = self.robots.get(robot_id)
        if r is None:
            raise KeyError(robot_id)
        r.cmd = (float(v_mps), float(omega_rps))
        r.cmd_stamp_ns = self.stamp_ns if stamp_ns is None else int(stamp_ns)

    def _command(self, r: RobotState) -> tuple[float, float]:
        """The command in force over the coming step: (0, 0) once it would lapse before the
        step ends."""
        ttl = self.p.command_ttl_ns
        stale = ttl is not None and self.stamp_ns + self.p.step_ns - r.cmd_stamp_ns > ttl
        if stale and not r.cmd_expired and r.cmd != (0.0, 0.0):
            r.commands_expired += 1
            log.warning("%s: its command is %.2f s old by the end of step %d: stopping it",
                        r.robot_id, (self.stamp_ns + self.p.step_ns - r.cmd_stamp_ns) / 1e9,
                        self.step)
        r.cmd_expired = stale
        return (0.0, 0.0) if stale else r.cmd

    # -- sensing ----------------------------------------------------------------------------
    def sense(self) -> Observation:
        ranges, odo, frames, beams = {}, {}, {}, {}
        discs = {rid: (r.pose[0], r.pose[1], self.p.drive.radius_m)
                 for rid, r in self.robots.items()}
        for rid, r in self.robots.items():
            lid = self.p.sensor(rid)
            others = np.array([d for k, d in discs.items() if k != rid]).reshape(-1, 3)
            heading = lid.heading_at(self.stamp_ns)
            sensor_pose = (r.pose[0], r.pose[1], r.pose[2] + heading)
            true = self.caster.cast(sensor_pose, lid.beams, lid.angle_min_rad,
                                    lid.angle_increment_rad, lid.cast_range_m, others)
            ranges[rid] = lid.noisy(true, r.rng_lidar)
            beams[rid] = BeamGeometry(lid.angle_min_at(self.stamp_ns), lid.angle_increment_rad,
                                      lid.range_min_m, lid.range_max_m)
            odo[rid] = (r.odom, r.v, r.w)
        cam = self.p.camera
        if cam.every_steps and self.step % cam.every_steps == 0:
            frames = self._render(discs)
        return Observation(self.step, self.stamp_ns, ranges, odo, frames, self.robots, beams)

    def _render(self, discs: dict[str, tuple[float, float, float]]) -> dict[str, Frame]:
        cam = self.p.camera
        poses = {rid: r.pose for rid, r in self.robots.items()}

        def blocked(p: tuple[float, float], q: tuple[float, float], a: str, b: str) -> bool:
            third = np.array([d for k, d in discs.items() if k not in (a, b)]).reshape(-1, 3)
            circles = np.vstack([self.world.circles, third]) if len(third) else self.world.circles
            return not line_of_sight(p, q, self.world.segments, circles)

        frames = {}
        for rid, r in self.robots.items():
            views = visible_tags(rid, poses, self.p.tags, self.p.mount, cam.camera,
                                 cam.max_range_m, cam.min_facing_cos, blocked)
            fake: dict[int, str] = {}
            if cam.spurious_rate > 0:
                views, fake = self._falsify(rid, poses, views, r.rng_camera)
            if not views:
                continue
            image = self.renderer.render(views, r.rng_camera, cam.blur_sigma_px, cam.noise_sigma)
            rel = [(v.observed, v.tag_id, between2(r.pose, poses[v.observed])) for v in views]
            frames[rid] = Frame(image, r.image_seq, views, rel, fake)
            r.image_seq += 1
        return frames

    def _falsify(self, rid: str, poses: dict[str, Pose], views: list[TagView],
                 rng: np.random.Generator) -> tuple[list[TagView], dict[int, str]]:
        """Replace each view, with probability ``spurious_rate``, by a false one: the tag of
        a robot that is not there ('id'), the robot drawn ≥ 1 m or ≥ 30° from where it is
        ('pose'); and add, with that probability, a tag hidden behind a wall ('occluded')."""
        cam = self.p.camera
        rate = cam.spurious_rate
        out: list[TagView] = []
        fake: dict[int, str] = {}
        others = [o for o in self.robots if o != rid]

        def clear(p: tuple[float, float], q: tuple[float, float], a: str, b: str) -> bool:
            return False

        for v in views:
            if rng.random() >= rate:
                out.append(v)
                continue
            kind = "id" if len(others) >= 2 and rng.random() < 0.5 else "pose"
            if kind == "id":
                wrong = [o for o in others if o != v.observed]
                who = wrong[int(rng.integers(len(wrong)))]
                tag = self.p.tags.tag_id(who, v.side)
                out.append(TagView(v.observer, v.observed, v.side, tag, v.plate_px,
                                   v.T_camera_tag, v.distance_m))
                fake[tag] = "id"
                continue
            x, y, t = poses[v.observed]
            if rng.random() < 0.5:
                ang, d = rng.uniform(-math.pi, math.pi), rng.uniform(1.0, 2.0)
                moved = (x + d * math.cos(ang), y + d * math.sin(ang), t)
            else:
                moved = (x, y, t + float(rng.choice([-1, 1])) * rng.uniform(0.52, 1.05))
            seen = visible_tags(rid, {**poses, v.observed: moved}, self.p.tags, self.p.mount,
                                cam.camera, cam.max_range_m, cam.min_facing_cos, clear)
            alt = [w for w in seen if w.observed == v.observed]
            if alt:
                out.append(alt[0])
                fake[alt[0].tag_id] = "pose"
            else:
                out.append(v)
        if rng.random() < rate:
            shown = {w.observed for w in out}
            hidden = [w for w in visible_tags(rid, poses, self.p.tags, self.p.mount,
                                              cam.camera, cam.max_range_m, cam.min_facing_cos,
                                              clear) if w.observed not in shown]
            if hidden:
                out.append(hidden[0])
                fake[hidden[0].tag_id] = "occluded"
        return out, fake

    # -- physics ----------------------------------------------------------------------------
    def advance(self) -> None:
        """Integrate from this step to the next one."""
        n = self.p.substeps
        dt = self.p.step_ns / 1e9 / n
        robots = list(self.robots.values())
        lim = self.p.drive
        # segments any robot could touch during this step (it moves at most v_max * step)
        reach = lim.radius_m + CONTACT_MARGIN_M + lim.v_max_mps * dt * n + 0.01
        pairs = self.obstacles.near(self._centres(), reach)
        noise = [r.rng_odom.standard_normal((n, 2)) for r in robots]
        cmds = [self._command(r) for r in robots]
        for i in range(n):
            moved = []
            for r, (v_cmd, w_cmd) in zip(robots, cmds, strict=True):
                r.v, r.w = limit_command(v_cmd, w_cmd, r.v, r.w, lim, dt)
                moved.append(arc_step(r.pose, r.v, r.w, dt))
            centres = np.array([m[:2] for m in moved]).reshape(-1, 2)
            hit = self.obstacles.touching(centres, lim.radius_m, pairs)
            near = hit
            if any(r.in_contact for r in robots):  # contact ends only clear of the obstacle
                near = self.obstacles.touching(centres, lim.radius_m + CONTACT_MARGIN_M, pairs)
            for r, new, h, c, z in zip(robots, moved, hit, near, noise, strict=True):
                if h:
                    if not r.in_contact:
                        r.collisions += 1
                        log.info("%s collided at (%.2f, %.2f)", r.robot_id, *r.pose[:2])
                    r.in_contact = True
                    r.v = r.w = 0.0
                    ds = dth = 0.0
                else:
                    r.in_contact = r.in_contact and bool(c)
                    r.pose = new
                    ds, dth = r.v * dt, r.w * dt
                    r.distance_m += abs(ds)
                mds, mdth = self.p.odometry.increment(ds, dth, r.bias, z[i])
                r.odom = arc_step(r.odom, mds, mdth, 1.0)
        self.step += 1
