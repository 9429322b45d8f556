"""``mrslam sim``: the simulator as its own process, speaking only over ``mrslam/sim/...``.

Each step it publishes the clock, every robot's camera frames, odometry and LIDAR sweep, and
the ground truth (also appended to ``<out>/truth.jsonl``). In real-time mode it paces steps at
``real_time_factor`` × real time and applies ``SimMotorCommand``s as they arrive. In lockstep
mode it waits (at start) until every robot's agent is alive, and (each step) until every live
agent has acknowledged the step, re-sending the step's messages when an ack is late; the command
inside the ack is the one applied. A robot whose agent disappears is stopped.

A command holds for ``command_ttl_s`` of simulated time from the step it arrived in (real time)
or the step its ack answered (lockstep), as the motor board's firmware holds a speed only for
its timeout: an agent that hangs, or an ack that times out, leaves its robot standing, not
driving blind on its last command.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import signal
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import msgspec

from schemas import (
    SimClock,
    SimGroundTruth,
    SimImage,
    SimLidar,
    SimMotorCommand,
    SimOdometry,
    SimStepAck,
    TruePose,
    TrueRelative,
    keys,
    quantise_ranges_mm,
)
from schemas.bus import Bus
from schemas.config_loading import load_config, write_resolved
from schemas.messages import Message
from schemas.ratelog import RateLimitedLog
from sim.camera import PinholeCamera
from sim.config import SimConfig, resolve_scene_sensors
from sim.errors import SimError
from sim.loader import load_world
from sim.odometry import OdometryNoise
from sim.robot import DriveLimits
from sim.simulator import (
    CameraSpec,
    LidarSpec,
    Observation,
    SimParams,
    Simulator,
    TowerSpec,
)

log = logging.getLogger(__name__)


def params_from_config(cfg: SimConfig, sensors: Mapping[str, str] | None = None) -> SimParams:
    """The simulation's parameters; ``sensors`` (robot id -> kind) default to ``cfg``'s."""
    lid, cam = cfg.lidar, cfg.camera
    step_s = 1.0 / lid.rate_hz
    kinds = cfg.sensors if sensors is None else sensors
    specs = {rid: depth_spec(cfg, kind) for rid, kind in kinds.items() if kind != "lidar"}
    return SimParams(
        step_ns=round(step_s * 1e9),
        substeps=max(1, round(cfg.physics_rate_hz * step_s)),
        lidar=LidarSpec(lid.beams, math.radians(lid.fov_deg), lid.range_min_m, lid.range_max_m,
                        lid.sigma_m),
        drive=DriveLimits(**cfg.drive.model_dump()),
        command_ttl_ns=round(cfg.command_ttl_s * 1e9),
        odometry=OdometryNoise(**cfg.odometry.model_dump()),
        camera=CameraSpec(
            camera=PinholeCamera.from_hfov(cam.width, cam.height, math.radians(cam.hfov_deg)),
            every_steps=max(1, round(lid.rate_hz / cam.rate_hz)) if cam.enabled else 0,
            max_range_m=cam.max_range_m, min_facing_cos=cam.min_facing_cos,
            blur_sigma_px=cam.blur_sigma_px, noise_sigma=cam.noise_sigma,
            spurious_rate=cam.spurious_rate),
        tags=cfg.tags, mount=cfg.camera_mount, sensors=specs)


def depth_spec(cfg: SimConfig, kind: str) -> LidarSpec:
    """The depth camera of ``cfg.depth``: on its tower (``depth``) or fixed forward
    (``depth-fixed``)."""
    d = cfg.depth
    tower = (TowerSpec(d.tower_positions, round(d.dwell_s * 1e9), round(d.turn_s * 1e9))
             if kind == "depth" else None)
    return LidarSpec(d.beams, math.radians(d.hfov_deg), d.range_min_m, d.range_max_m, d.sigma_m,
                     d.sigma_per_m2, depth=True, tower=tower)


def step_messages(sim: Simulator, obs: Observation, world_name: str, lockstep: bool = False,
                  real_time_factor: float = 1.0
                  ) -> tuple[list[tuple[str, Message]], SimGroundTruth]:
    """Every message of one step, in publishing order, and the ground truth."""
    p = sim.p
    msgs: list[tuple[str, Message]] = [(keys.SIM_CLOCK, SimClock(
        seq=obs.step, stamp_ns=obs.stamp_ns, step=obs.step, dt_ns=p.step_ns, lockstep=lockstep,
        real_time_factor=0.0 if lockstep else real_time_factor))]
    relatives = []
    for rid in sim.robots:
        frame = obs.frames.get(rid)
        if frame is not None:
            cam = p.camera.camera
            h, w = frame.image.shape
            msgs.append((keys.sim_image(rid), SimImage(
                robot_id=rid, seq=frame.seq, stamp_ns=obs.stamp_ns, width=w, height=h,
                fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, data=frame.image.tobytes())))
            relatives += [TrueRelative(observer_id=rid, observed_id=other, tag_id=tag,
                                       relative_pose=rel, image_seq=frame.seq,
                                       spurious=frame.spurious.get(tag, ""))
                          for other, tag, rel in frame.relatives]
        pose, v, w = obs.odometry[rid]
        msgs.append((keys.sim_odom(rid), SimOdometry(
            robot_id=rid, seq=obs.step, stamp_ns=obs.stamp_ns, pose=pose, v_mps=v,
            omega_rps=w)))
        lid = obs.beams[rid]
        msgs.append((keys.sim_lidar(rid), SimLidar(
            robot_id=rid, seq=obs.step, stamp_ns=obs.stamp_ns, angle_min_rad=lid.angle_min_rad,
            angle_increment_rad=lid.angle_increment_rad,
            range_min_mm=round(lid.range_min_m * 1000), range_max_mm=round(lid.range_max_m * 1000),
            ranges_mm=quantise_ranges_mm(obs.ranges_m[rid], lid.range_min_m, lid.range_max_m),
            lockstep=lockstep)))
    truth = SimGroundTruth(seq=obs.step, stamp_ns=obs.stamp_ns, world=world_name, poses=[
        TruePose(robot_id=r.robot_id, pose=r.pose, collisions=r.collisions,
                 distance_m=r.distance_m) for r in obs.truth.values()], relatives=relatives)
    return msgs, truth


class SimNode:
    """The simulator on the bus: publishes steps, collects commands and acks."""

    def __init__(self, bus: Bus, sim: Simulator, cfg: SimConfig, world_name: str,
                 truth_out: IO[bytes] | None = None) -> None:
        self.bus, self.sim, self.cfg = bus, sim, cfg
        self.world_name = world_name
        self.truth_out = truth_out
        self.cond = threading.Condition()
        # commands as (v, ω, simulation time given)
        self.motor: dict[str, tuple[float, float, int]] = {}
        self.acked: dict[str, int] = dict.fromkeys(sim.robots, -1)
        self.ack_cmd: dict[str, tuple[float, float, int]] = {}
        self.alive: set[str] = set()
        self.started: float | None = None   # monotonic time of the first step
        self._log = RateLimitedLog(log)
        self._were_alive: set[str] = set()
        self.counters = {"ack_timeouts": 0, "resends": 0, "images": 0, "foreign_messages": 0,
                         "late_steps": 0, "held_s": 0.0}
        bus.subscribe(keys.SIM_ALL_MOTOR, SimMotorCommand, self._on_motor)
        bus.subscribe(keys.SIM_ALL_ACK, SimStepAck, self._on_ack)
        bus.watch_alive(keys.ALL_ALIVE, self._on_alive)
        bus.declare_alive(keys.SIM_ALIVE)

    # -- callbacks (Zenoh threads) ----------------------------------------------------------
    def _ours(self, key: str, robot_id: str) -> bool:
        if keys.robot_id_of(key) != robot_id or robot_id not in self.sim.robots:
            self.counters["foreign_messages"] += 1
            self._log.warning("foreign", "ignoring a message for robot %s on %s", robot_id, key)
            return False
        return True

    def _on_motor(self, key: str, msg: SimMotorCommand) -> None:
        if self._ours(key, msg.robot_id):
            with self.cond:
                self.motor[msg.robot_id] = (msg.v_mps, msg.omega_rps, self.sim.stamp_ns)

    def _on_ack(self, key: str, msg: SimStepAck) -> None:
        if not self._ours(key, msg.robot_id):
            return
        with self.cond:
            if msg.step > self.acked[msg.robot_id]:
                self.acked[msg.robot_id] = msg.step
                # an ack without a command renews the one before
                v, w, _ = self.ack_cmd.get(msg.robot_id, (0.0, 0.0, 0))
                if msg.v_mps is not None and msg.omega_rps is not None:
                    v, w = msg.v_mps, msg.omega_rps
                self.ack_cmd[msg.robot_id] = (v, w, msg.step * self.sim.p.step_ns)
            self.cond.notify_all()

    def _on_alive(self, key: str, alive: bool) -> None:
        rid = keys.robot_id_of(key)
        if rid is None or rid not in self.sim.robots:
            return
        with self.cond:
            if alive:
                self.alive.add(rid)
            else:
                self.alive.discard(rid)
                self.motor[rid] = self.ack_cmd[rid] = (0.0, 0.0, self.sim.stamp_ns)
                log.warning("agent of %s is gone; stopping the robot", rid)
            self.cond.notify_all()

    # -- the loop ---------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        cfg, sim = self.cfg, self.sim
        if cfg.lockstep:
            self._wait_for_agents(stop)
        period_s = sim.p.step_ns / 1e9 / cfg.real_time_factor
        t0 = self.started = time.monotonic()
        k0 = sim.step
        while not stop.is_set() and not self._finished():
            if cfg.lockstep:
                self._hold_while_alone(stop)
            obs = sim.sense()
            msgs, truth = step_messages(sim, obs, self.world_name, cfg.lockstep,
                                        cfg.real_time_factor)
            self._publish(msgs, truth)
            if cfg.lockstep:
                self._wait_for_acks(obs.step, msgs, stop)
            else:
                late = t0 + (sim.step + 1 - k0) * period_s - time.monotonic()
                if late > 0:
                    stop.wait(late)
                elif late < -1.0:  # far behind: do not try to catch up in a burst
                    self.counters["late_steps"] += 1
                    t0, k0 = time.monotonic(), sim.step + 1
            with self.cond:
                commands = dict(self.ack_cmd if cfg.lockstep else self.motor)
            for rid, (v, w, stamp_ns) in commands.items():
                sim.set_command(rid, v, w, stamp_ns)
            sim.advance()

    def _finished(self) -> bool:
        cfg, sim = self.cfg, self.sim
        if cfg.max_steps is not None and sim.step >= cfg.max_steps:
            return True
        return cfg.duration_s is not None and sim.stamp_ns >= cfg.duration_s * 1e9

    def _publish(self, msgs: list[tuple[str, Message]], truth: SimGroundTruth) -> None:
        block = self.cfg.lockstep
        for key, msg in msgs:
            self.bus.publish(key, msg, block=block)
            if isinstance(msg, SimImage):
                self.counters["images"] += 1
        self.bus.publish(keys.SIM_TRUTH, truth, block=block)
        if self.truth_out is not None:
            self.truth_out.write(msgspec.json.encode(truth) + b"\n")

    def _wait_for_agents(self, stop: threading.Event) -> None:
        deadline = time.monotonic() + self.cfg.start_timeout_s
        with self.cond:
            while not stop.is_set() and self.alive != set(self.sim.robots):
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = sorted(set(self.sim.robots) - self.alive)
                    raise SimError(f"lockstep: no agent for {', '.join(missing)} after "
                                   f"{self.cfg.start_timeout_s:g} s")
                self.cond.wait(min(left, 0.1))
        log.info("lockstep: all %d agents are alive", len(self.sim.robots))

    def _hold_while_alone(self, stop: threading.Event) -> None:
        """Lockstep with no agent alive — the router (the server) went away, or every agent
        stopped — the world waits rather than run on with the robots standing. When agents
        come back it waits a moment more for the others that were there before."""
        with self.cond:
            if self.alive or stop.is_set():
                self._were_alive = set(self.alive)
                return
            log.warning("lockstep: no agent is alive; the simulation holds")
            t0 = time.monotonic()
            while not stop.is_set() and not self.alive:
                self.cond.wait(0.1)
            grace = time.monotonic() + self.cfg.ack_timeout_s
            while not stop.is_set() and self.alive < self._were_alive \
                    and time.monotonic() < grace:
                self.cond.wait(0.05)
            self.counters["held_s"] += time.monotonic() - t0
            log.warning("lockstep: agents back (%s) after %.1f s; the simulation goes on",
                        ", ".join(sorted(self.alive)), time.monotonic() - t0)

    def _wait_for_acks(self, step: int, msgs: list[tuple[str, Message]],
                       stop: threading.Event) -> None:
        t0 = time.monotonic()
        resend_at = t0 + self.cfg.resend_after_s
        with self.cond:
            while not stop.is_set():
                missing = [r for r in self.alive if self.acked[r] < step]
                if not missing:
                    return
                now = time.monotonic()
                if now - t0 > self.cfg.ack_timeout_s:
                    self.counters["ack_timeouts"] += 1
                    log.warning("lockstep: no ack for step %d from %s after %g s; going on",
                                step, ", ".join(sorted(missing)), self.cfg.ack_timeout_s)
                    return
                if now >= resend_at:
                    self.counters["resends"] += 1
                    resend_at = now + self.cfg.resend_after_s
                    self.cond.release()
                    try:
                        for key, msg in msgs:
                            if keys.robot_id_of(key) in (None, *missing):
                                self.bus.publish(key, msg, block=True)
                    finally:
                        self.cond.acquire()
                self.cond.wait(min(0.05, max(resend_at - now, 0.001)))

    def summary(self, wall_s: float) -> dict[str, Any]:
        sim = self.sim
        sim_s = sim.stamp_ns / 1e9
        stepping = time.monotonic() - self.started if self.started is not None else 0.0
        return {
            "world": self.world_name, "steps": sim.step, "sim_time_s": sim_s, "wall_s": wall_s,
            "stepping_wall_s": stepping,
            "real_time_factor": sim_s / stepping if stepping > 0 else None,
            "lockstep": self.cfg.lockstep, "seed": self.cfg.seed,
            "robots": {rid: {"pose": list(r.pose), "collisions": r.collisions,
                             "distance_m": r.distance_m, "images": r.image_seq,
                             "commands_expired": r.commands_expired}
                       for rid, r in sim.robots.items()},
            **self.counters,
            "commands_expired": sum(r.commands_expired for r in sim.robots.values()),
            "bus": self.bus.stats.as_dict(),
        }


def build(cfg: SimConfig) -> tuple[Simulator, str]:
    world_path, robots, sensors = resolve_scene_sensors(cfg)
    world = load_world(world_path, list(cfg.model_path), cfg.lidar.height_m)
    if sensors:
        log.info("range sensors: %s", ", ".join(f"{r} {k}" for r, k in sorted(sensors.items())))
    return Simulator(world, robots, params_from_config(cfg, sensors), cfg.seed), world.name


def run(config: str | Path | None = None, overrides: Mapping[str, Any] | None = None,
        stop: threading.Event | None = None) -> dict[str, Any]:
    """Run the simulator until ``stop`` is set, ``duration_s``/``max_steps`` is reached, or
    SIGINT/SIGTERM; returns the summary (also written to ``<out>/summary.json``)."""
    cfg = load_config(SimConfig, config, overrides)
    sim, world_name = build(cfg)
    stop = stop or threading.Event()
    out = Path(cfg.out) if cfg.out else None
    if out is not None:
        write_resolved(cfg, out)
    t0 = time.monotonic()
    with contextlib.ExitStack() as stack:
        truth = stack.enter_context(open(out / "truth.jsonl", "wb")) if out else None
        bus = stack.enter_context(Bus.from_config(cfg.bus))
        node = SimNode(bus, sim, cfg, world_name, truth)
        stack.enter_context(_stop_on_signals(stop))
        log.info("simulating %s with %s (%s)", world_name, ", ".join(sim.robots),
                 "lockstep" if cfg.lockstep else f"x{cfg.real_time_factor:g} real time")
        try:
            node.run(stop)
        except KeyboardInterrupt:
            log.info("interrupted")
        summary = node.summary(time.monotonic() - t0)
    if out is not None:
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGTERM sets ``stop`` (main thread only); the previous handler is restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
