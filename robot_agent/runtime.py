"""The agent on each robot: sweeps and tags out, velocity commands in, a watchdog in between.

The backend's sensor callbacks only queue events; one thread handles them in arrival order:

- a sweep becomes a ``Scan`` with the wheel-odometry pose at its time; in lockstep the step is
  then acknowledged (after the server's command for it, when a server is alive and
  ``lockstep.wait_for_command`` is set; bounded by ``command_timeout_s`` of wall time, and by
  ``first_command_timeout_s`` until the server's first command, which a server starting on a
  busy machine may be slow to send);
- a camera frame goes through the ArUco detector and becomes ``TagDetections``.

Commands (``VelocityCommand`` on ``mrslam/robot/<id>/cmd_vel``) go straight to the base once
``CommandGate`` has checked that they come from the server the agent is bound to; others are
counted (``commands_ignored_<reason>``) and logged at a limited rate. The watchdog stops the
base when a command's time-to-live runs out on the robot's clock or when the server's
liveliness token disappears. Liveliness ``mrslam/robot/<id>/alive`` and a
``RobotStatus`` every ``status_period_s`` tell the world the agent is there.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import signal
import threading
import time
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import msgspec

from robot_agent.aruco import Sighting, SigmaModel, TagDetector, in_line_of_sight, lidar_fix
from robot_agent.backend import Backend, Frame, Sweep
from robot_agent.command_gate import CommandGate, Reason
from robot_agent.config import AgentConfig
from robot_agent.watchdog import Watchdog
from schemas import RobotStatus, Scan, TagDetection, TagDetections, VelocityCommand, keys
from schemas.bus import Bus
from schemas.config_loading import load_config
from schemas.messages import RobotState
from schemas.ratelog import RateLimitedLog
from schemas.se2 import wrap_angle

log = logging.getLogger(__name__)

#: frames with sightings held for the next sweep at most (a camera may run faster than the
#: LIDAR); past this the oldest is sent with what the last sweep can tell
MAX_PENDING_FRAMES = 8


class Agent:
    def __init__(self, cfg: AgentConfig, bus: Bus, backend: Backend) -> None:
        self.cfg, self.bus, self.backend = cfg, bus, backend
        self.rid = cfg.robot_id
        d = cfg.detector
        self.detector = TagDetector(cfg.tags, cfg.camera_mount, SigmaModel(
            d.range_a_m, d.range_b_per_m, d.bearing_a_rad, d.bearing_b_rad_per_m, d.yaw_a_rad,
            d.yaw_b_rad_per_m2, d.ambiguous_ratio, d.ambiguous_sigma_yaw_rad),
            d.max_reprojection_px) if d.enabled else None
        self.events: queue.Queue[Sweep | Frame] = queue.Queue()
        self.cond = threading.Condition()
        self.watchdog = Watchdog()
        self.command: tuple[float, float] = (0.0, 0.0)
        self.last_command_stamp_ns = -1
        self.awaiting_first_command = True   # the first wait is first_command_timeout_s
        self.server_alive = False
        self.gate = CommandGate(self.rid, cfg.command_max_age_s, cfg.command_max_ahead_s)
        self._ignored_log = RateLimitedLog(log)
        self.counters: Counter[str] = Counter()
        self.seq: Counter[str] = Counter()
        self.last_sweep_wall = 0.0
        self.last_sweep: Sweep | None = None
        self.prev_sweep: Sweep | None = None
        #: frames' sightings waiting for the sweep of their moment (stamp, sightings)
        self.pending_sightings: list[tuple[int, list[Sighting]]] = []
        self._status_cpu = (time.monotonic(), time.process_time())

    def start(self) -> None:
        # who the server is before its commands: the first one is not dropped as unknown
        # (a split server's workers first: their sessions hold the server's token too)
        self.bus.watch_alive(keys.ALL_CLUSTER_WORKER_SESSIONS, self._on_worker_session)
        self.bus.watch_alive(keys.cluster_owners(self.rid), self._on_owner)
        self.bus.watch_holders(keys.SERVER_ALIVE, self._on_server_holder)
        self.bus.watch_alive(keys.SERVER_ALIVE, self._on_server)
        self.bus.subscribe_with_source(keys.robot_cmd_vel(self.rid), VelocityCommand,
                                       self._on_command)
        self.backend.lidar.start(self.events.put)
        if self.backend.camera is not None:
            self.backend.camera.start(self._queue_frame)
        self.bus.declare_alive(keys.robot_alive(self.rid))   # last: we are ready for step 0
        log.info("agent %s up", self.rid)

    # -- the loop ---------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        next_status = time.monotonic()
        while not stop.is_set():
            try:
                event = self.events.get(timeout=0.05)
            except queue.Empty:
                event = None
            if isinstance(event, Sweep):
                self.handle_sweep(event)
            elif isinstance(event, Frame):
                self.handle_frame(event)
            self.check_watchdog(self.backend.monotonic_ns())
            if time.monotonic() >= next_status:
                self.publish_status()
                next_status = time.monotonic() + self.cfg.status_period_s
        self.set_velocity(0.0, 0.0)

    def handle_sweep(self, sweep: Sweep) -> None:
        self.check_watchdog(self.backend.monotonic_ns())
        if self.last_sweep is not None and sweep.stamp_ns < self.last_sweep.stamp_ns:
            with self.cond:   # the robot's clock went back: commands answer the new stamps
                self.last_command_stamp_ns = -1
        self.last_sweep_wall = time.monotonic()
        self.prev_sweep, self.last_sweep = self.last_sweep, sweep
        # the sightings waiting for this sweep go first: when a step's scan reaches a lockstep
        # server, the robot's sightings of that step are already there
        pending, self.pending_sightings = self.pending_sightings, []
        for stamp, sightings in pending:
            near = min((s for s in (self.prev_sweep, sweep) if s is not None),
                       key=lambda s: abs(s.stamp_ns - stamp))
            self._publish_sightings(stamp, sightings, near)
        odom = self.backend.base.odometry_at(sweep.stamp_ns)
        if odom is None:
            self.counters["sweeps_without_odometry"] += 1
        else:
            self.publish(keys.robot_scan(self.rid), Scan(
                robot_id=self.rid, seq=self._next("scan"), stamp_ns=sweep.stamp_ns,
                odom_pose=odom.pose, angle_min_rad=sweep.angle_min_rad,
                angle_increment_rad=sweep.angle_increment_rad, range_min_mm=sweep.range_min_mm,
                range_max_mm=sweep.range_max_mm, ranges_mm=sweep.ranges_mm))
            self.counters["scans_sent"] += 1
        sync = self.backend.sync
        if sweep.step is not None and sync is not None and sync.lockstep():
            self._wait_for_command(sweep.stamp_ns)
            with self.cond:
                command = self.command
            sync.ack(sweep.step, command)

    def _wait_for_command(self, stamp_ns: int) -> None:
        """Lockstep with a server: hold the ack until the command answering this scan."""
        if not self.cfg.lockstep.wait_for_command:
            return
        with self.cond:
            lock = self.cfg.lockstep
            first = self.awaiting_first_command and self.last_command_stamp_ns < 0
            wait_s = max(lock.command_timeout_s, lock.first_command_timeout_s) if first \
                else lock.command_timeout_s
            deadline = time.monotonic() + wait_s
            while self.server_alive and self.last_command_stamp_ns < stamp_ns:
                left = deadline - time.monotonic()
                if left <= 0:
                    self.counters["command_timeouts"] += 1
                    self.awaiting_first_command = False   # a server that answers nobody
                    log.warning("no command for the scan at %d ns within %g s; acking anyway",
                                stamp_ns, wait_s)
                    return
                self.cond.wait(left)

    def handle_frame(self, frame: Frame) -> None:
        if self.detector is None:
            return
        try:
            found = self.detector.detect(frame.image, frame.K, self.rid, frame.dist)
        except Exception as e:  # a broken frame must not stop the agent
            self.counters["detector_errors"] += 1
            log.warning("tag detection failed: %s: %s", type(e).__name__, e)
            return
        self.counters["tags_rejected"] += len(found.rejected)
        if not found.sightings:
            return
        d, sweep = self.cfg.detector, self.last_sweep
        if d.lidar_fix and d.body_radius_m > 0 and (
                sweep is None or frame.stamp_ns - sweep.stamp_ns > d.lidar_fix_max_age_s * 1e9):
            # the sweep of this moment is still to come (a simulator sends a step's frames
            # before its sweep; a LIDAR may lag the camera): finish the frame with it
            if len(self.pending_sightings) >= MAX_PENDING_FRAMES:   # no sweeps coming
                self._publish_sightings(*self.pending_sightings.pop(0), sweep)
            self.pending_sightings.append((frame.stamp_ns, found.sightings))
            return
        self._publish_sightings(frame.stamp_ns, found.sightings, sweep)

    def _publish_sightings(self, stamp_ns: int, found: list[Sighting],
                           sweep: Sweep | None) -> None:
        # the LIDAR fix first: past ~5 m a tag's biased range puts the robot's own body
        # closer than the tag, and the line-of-sight check would take it for a wall
        located = [self._detection(s, stamp_ns, sweep) for s in found[:64]]
        dets = [d for d in located if self._in_sight(d.range_m, d.bearing_rad, stamp_ns, sweep)]
        self.counters["tags_occluded"] += len(located) - len(dets)
        if not dets:
            return
        self.publish(keys.robot_tags(self.rid), TagDetections(
            robot_id=self.rid, seq=self._next("tags"), stamp_ns=stamp_ns, detections=dets))
        self.counters["tag_detections"] += len(dets)

    def _detection(self, s: Sighting, stamp_ns: int, sweep: Sweep | None) -> TagDetection:
        """The sighting as sent; range and bearing from the LIDAR where it confirms them."""
        det = TagDetection(tag_id=s.tag_id, observed_robot_id=s.robot_id, range_m=s.range_m,
                           bearing_rad=s.bearing_rad, yaw_rad=s.yaw_rad,
                           sigma_range_m=s.sigma_range_m, sigma_bearing_rad=s.sigma_bearing_rad,
                           sigma_yaw_rad=s.sigma_yaw_rad,
                           reprojection_error_px=s.reprojection_error_px)
        d = self.cfg.detector
        if not d.lidar_fix or d.body_radius_m <= 0 or sweep is None or \
                abs(sweep.stamp_ns - stamp_ns) > d.lidar_fix_max_age_s * 1e9:
            return det
        turn = self._turn_since(sweep, stamp_ns)
        ranges, angles = sweep.polar()
        fix = lidar_fix(s.range_m, s.bearing_rad + turn, ranges, angles, d.body_radius_m,
                        d.lidar_sigma_m)
        if fix is None:
            self.counters["tags_not_lidar_fixed"] += 1
            return det
        self.counters["tags_lidar_fixed"] += 1
        return msgspec.structs.replace(
            det, range_m=fix.range_m, bearing_rad=wrap_angle(fix.bearing_rad - turn),
            sigma_range_m=fix.sigma_range_m, sigma_bearing_rad=fix.sigma_bearing_rad,
            located_by="lidar")

    def _turn_since(self, sweep: Sweep, stamp_ns: int) -> float:
        """How far the robot turned from the sweep's time to ``stamp_ns`` (odometry)."""
        at_frame = self.backend.base.odometry_at(stamp_ns)
        at_sweep = self.backend.base.odometry_at(sweep.stamp_ns)
        if at_frame is None or at_sweep is None:
            return 0.0
        return float(at_frame.pose[2] - at_sweep.pose[2])

    def _in_sight(self, range_m: float, bearing_rad: float, stamp_ns: int,
                  sweep: Sweep | None) -> bool:
        """The line-of-sight check against the scan (turned by odometry to the frame's time);
        without a recent scan the sighting is kept (the server verifies it too)."""
        d = self.cfg.detector
        if not d.line_of_sight or sweep is None or \
                abs(sweep.stamp_ns - stamp_ns) > d.los_max_age_s * 1e9:
            return True
        turn = self._turn_since(sweep, stamp_ns)
        ranges, angles = sweep.polar()
        return in_line_of_sight(range_m, bearing_rad + turn, ranges, angles,
                                math.radians(d.los_half_width_deg), d.los_margin_m)

    def _queue_frame(self, frame: Frame) -> None:
        if self.events.qsize() > self.cfg.max_queued_frames and not self._lockstep():
            self.counters["frames_dropped"] += 1  # busy: a late frame is worth little
            return
        self.events.put(frame)

    def _lockstep(self) -> bool:
        return self.backend.sync is not None and self.backend.sync.lockstep()

    # -- commands and the watchdog ----------------------------------------------------------
    def _on_command(self, key: str, msg: VelocityCommand, source: str | None) -> None:
        with self.cond:
            now_ns = self.backend.now_ns()
            reason = self.gate.check(msg, source, now_ns)
            if reason is not None:
                self._ignore(reason, msg, source, now_ns)
                return
        v = min(max(msg.v_mps, -self.cfg.v_max_mps), self.cfg.v_max_mps)
        w = min(max(msg.omega_rps, -self.cfg.omega_max_rps), self.cfg.omega_max_rps)
        with self.cond:
            self.watchdog.feed(self.backend.monotonic_ns(), msg.ttl_s)
            self.counters["commands_received"] += 1
            self.last_command_stamp_ns = max(self.last_command_stamp_ns, msg.stamp_ns)
            self.awaiting_first_command = False
            self.set_velocity(v, w)
            self.cond.notify_all()

    def _ignore(self, reason: Reason, msg: VelocityCommand, source: str | None,
                now_ns: int) -> None:
        """Count an ignored command; log the first five of a kind, then one line per 10 s."""
        name = "foreign_commands" if reason == "other_robot" else f"commands_ignored_{reason}"
        self.counters[name] += 1
        self.counters["commands_ignored"] += 1
        self._ignored_log.warning(
            reason, "ignored command (%s, %d of this kind, %d in all): for %s, stamp %d ns at "
            "robot time %d ns, from session %s; the server is %s", reason, self.counters[name],
            self.counters["commands_ignored"], msg.robot_id, msg.stamp_ns, now_ns,
            source or "unknown", self.gate.server or "not known")

    def _on_server_holder(self, zid: str, alive: bool) -> None:
        with self.cond:
            before = self.gate.server
            now = self.gate.server_holder(zid, alive)
            others = self.gate.holders[1:]
            split = bool(self.gate.workers)
        self._log_bound(before, now)
        if alive and zid in others and not split:
            log.warning("session %s also holds the server's liveliness token; its commands "
                        "are ignored while %s lives", zid, now)

    def _on_worker_session(self, key: str, alive: bool) -> None:
        parsed = keys.cluster_worker_session_of(key)
        if parsed is not None:
            with self.cond:
                before = self.gate.server
                now = self.gate.worker_session(*parsed, alive)
            self._log_bound(before, now)

    def _on_owner(self, key: str, alive: bool) -> None:
        parsed = keys.cluster_owner_of(key)
        if parsed is not None and parsed[0] == self.rid:
            with self.cond:
                before = self.gate.server
                now = self.gate.owner(parsed[1], alive)
            self._log_bound(before, now)

    def _log_bound(self, before: str | None, now: str | None) -> None:
        if now != before:
            log.info("bound to the server session %s", now) if now else \
                log.warning("no server session holds the server's token")

    def _on_server(self, key: str, alive: bool) -> None:
        with self.cond:
            was = self.server_alive
            self.server_alive = alive
            if was and not alive and self.cfg.stop_on_server_loss:
                log.warning("server liveliness lost: stopping")
                self.watchdog.server_lost()
                self.set_velocity(0.0, 0.0)
            self.cond.notify_all()

    def check_watchdog(self, now_ns: int) -> None:
        with self.cond:
            if self.watchdog.expired(now_ns):
                log.info("commands stopped arriving: stopping")
                self.set_velocity(0.0, 0.0)

    def set_velocity(self, v: float, w: float) -> None:
        with self.cond:
            self.command = (v, w)
        self.backend.base.set_velocity(v, w)

    # -- output -----------------------------------------------------------------------------
    def _next(self, name: str) -> int:
        n = self.seq[name]
        self.seq[name] += 1
        return n

    def publish(self, key: str, msg: Any) -> None:
        self.bus.publish(key, msg, block=self._lockstep())

    def errors(self) -> int:
        s = self.bus.stats
        return (sum(s.rejected.values()) + sum(s.callback_errors.values())
                + self.counters["detector_errors"] + self.counters["commands_ignored"]
                + sum(self.backend.counters().values()))

    def publish_status(self) -> None:
        t, cpu = time.monotonic(), time.process_time()
        t0, cpu0 = self._status_cpu
        self._status_cpu = (t, cpu)
        fresh = self.last_sweep_wall and t - self.last_sweep_wall < 3.0
        state: RobotState = ("ok" if fresh else "starting" if not self.last_sweep_wall
                             else "degraded")
        message = "" if fresh else "no LIDAR sweeps"
        self.bus.publish(keys.robot_status(self.rid), RobotStatus(
            robot_id=self.rid, seq=self._next("status"), stamp_ns=self.backend.now_ns(),
            state=state, message=message,
            cpu_percent=min(max(100.0 * (cpu - cpu0) / max(t - t0, 1e-6), 0.0), 10000.0),
            rss_mb=_rss_mb(), scans_sent=self.counters["scans_sent"],
            commands_received=self.counters["commands_received"], errors=self.errors()))

    def summary(self) -> dict[str, Any]:
        return {"robot_id": self.rid, **dict(self.counters),
                "watchdog_timeouts": self.watchdog.timeouts,
                "server_losses": self.watchdog.server_losses,
                "backend": self.backend.counters(), "bus": self.bus.stats.as_dict()}


def _rss_mb() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except (OSError, ValueError, IndexError):
        return 0.0


def make_backend(cfg: AgentConfig, bus: Bus) -> Backend:
    if cfg.backend == "sim":
        from robot_agent.sim_backend import sim_backend

        return sim_backend(bus, cfg.robot_id, cfg.sim_clock_steps, cfg.sim_odometry_at_zero)
    if cfg.backend == "hardware":
        from robot_agent.hardware import hardware_backend

        return hardware_backend(cfg.hardware)
    raise NotImplementedError(f"backend {cfg.backend}")


def run(config: str | Path | None = None, overrides: Mapping[str, Any] | None = None,
        stop: threading.Event | None = None) -> dict[str, Any]:
    """Run the agent until ``stop`` is set (or Ctrl-C); returns its counters."""
    cfg = load_config(AgentConfig, config, overrides)
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with Bus.from_config(cfg.bus) as bus:
        backend = make_backend(cfg, bus)
        agent = Agent(cfg, bus, backend)
        agent.start()
        try:
            agent.run(stop)
        except KeyboardInterrupt:
            log.info("interrupted")
            agent.set_velocity(0.0, 0.0)
        finally:
            backend.close()
        return agent.summary()
