"""The simulator backend: the robot's LIDAR, base and camera are messages on ``mrslam/sim/...``.

The simulator publishes, per step and robot, any camera frames, then the odometry, then the
sweep (see ``schemas.sim``). One subscriber on ``mrslam/sim/robot/<id>/*`` receives them on one
thread in that order, so a sweep always finds its odometry and follows its step's frames. The
robot's monotonic clock is the latest simulation time seen; its own clock, which stamps what it
sends, is the same unless ``clock_steps`` makes it step (to try how the server copes with a
robot whose clock is corrected by NTP or boots in 1970). A sweep the simulator re-sends (its ack was
late or lost) is not handed to the agent again; the step's ack is re-sent instead. Payloads that
do not decode are counted and logged, never passed on.

The odometry is the simulator's, which starts at the robot's spawn pose and runs on for the whole
simulation. With ``odometry_at_zero`` it is taken relative to the first pose this backend sees,
as a real robot's wheel odometry starts at zero when it boots: an agent restarted mid-run (a
robot rebooted) then reports odometry that has nothing to do with what its previous run sent.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter, deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from robot_agent.backend import Backend, Frame, Odometry, Pose, Sweep
from schemas import (
    SchemaError,
    SimImage,
    SimLidar,
    SimMotorCommand,
    SimOdometry,
    SimStepAck,
    decode,
    keys,
)
from schemas.bus import Bus
from schemas.se2 import between

log = logging.getLogger(__name__)


class SimBackend:
    """LIDAR source, base, camera and step sync of one simulated robot."""

    def __init__(self, bus: Bus, robot_id: str,
                 clock_steps: Sequence[tuple[float, float]] = (),
                 odometry_at_zero: bool = False) -> None:
        self.bus = bus
        self.robot_id = robot_id
        self._odometry_at_zero = odometry_at_zero
        self._odom_origin: Pose | None = None   # the simulator's odometry where ours is zero
        #: (sim time [ns], step [ns]): from that time on, the robot's clock is off by the step
        self._clock_steps = sorted((round(at * 1e9), round(d * 1e9)) for at, d in clock_steps)
        self._lock = threading.Lock()
        self._now_ns = 0
        self._lockstep = False
        self._odom: deque[Odometry] = deque(maxlen=64)   # stamped by the robot's clock
        self._sim_odom = -1                               # sim time of the newest odometry
        self._last_sweep_seq = -1
        self._last_frame_stamp = -1
        self._last_ack: SimStepAck | None = None
        self._ack_seq = 0
        self._motor_seq = 0
        self._on_sweep: Callable[[Sweep], None] | None = None
        self._on_frame: Callable[[Frame], None] | None = None
        self.counters: Counter[str] = Counter()
        prefix = keys.sim_lidar(robot_id).rsplit("/", 1)[0]
        self._handlers: dict[str, tuple[type[Any], Callable[[Any], None]]] = {
            "odom": (SimOdometry, self._odometry), "image": (SimImage, self._image),
            "lidar": (SimLidar, self._lidar)}
        self._sub = bus.session.declare_subscriber(f"{prefix}/*", self._on_sample)

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception as e:  # the session may be gone already
            log.debug("undeclaring the sim subscriber: %s", e)

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        handler = self._handlers.get(key.rsplit("/", 1)[-1])
        if handler is None:
            return  # our own motor commands and acks
        cls, fn = handler
        try:
            msg = decode(sample.payload.to_bytes(), cls)
        except SchemaError as e:
            self.counters["rejected"] += 1
            if self.counters["rejected"] <= 10:
                log.warning("rejected message on %s: %s", key, e)
            return
        if msg.robot_id != self.robot_id:
            self.counters["foreign_messages"] += 1
            return
        try:
            fn(msg)
        except Exception:  # never raise into Zenoh's thread
            self.counters["handler_errors"] += 1
            log.exception("handling %s failed", key)

    # -- interfaces -------------------------------------------------------------------------
    def start(self, on_sweep: Callable[[Sweep], None]) -> None:  # LidarSource
        self._on_sweep = on_sweep

    def start_camera(self, on_frame: Callable[[Frame], None]) -> None:  # Camera
        self._on_frame = on_frame

    def odometry_at(self, stamp_ns: int) -> Odometry | None:  # Base
        with self._lock:
            for o in reversed(self._odom):
                if o.stamp_ns <= stamp_ns:
                    return o
        return None

    def set_velocity(self, v_mps: float, omega_rps: float) -> None:  # Base
        with self._lock:
            self._motor_seq += 1
            msg = SimMotorCommand(robot_id=self.robot_id, seq=self._motor_seq,
                                  stamp_ns=self._now_ns, v_mps=v_mps, omega_rps=omega_rps)
        self.bus.publish(keys.sim_motor(self.robot_id), msg, block=True)

    def now_ns(self) -> int:
        return self._robot_ns(self._now_ns)

    def sim_ns(self) -> int:
        return self._now_ns

    def _robot_ns(self, sim_ns: int) -> int:
        """The robot's own clock at simulation time ``sim_ns``."""
        return sim_ns + sum(d for at, d in self._clock_steps if sim_ns >= at)

    def lockstep(self) -> bool:  # StepSync
        return self._lockstep

    def ack(self, step: int, command: tuple[float, float]) -> None:  # StepSync
        with self._lock:
            self._ack_seq += 1
            msg = SimStepAck(robot_id=self.robot_id, seq=self._ack_seq, stamp_ns=self._now_ns,
                             step=step, v_mps=command[0], omega_rps=command[1])
            self._last_ack = msg
        self.bus.publish(keys.sim_ack(self.robot_id), msg, block=True)

    # -- messages, in the order the simulator sent them ---------------------------------------
    def _odometry(self, msg: SimOdometry) -> None:
        with self._lock:
            if self._odom and msg.stamp_ns < self._sim_odom:
                log.warning("simulation time went back to %d ns: a new simulation", msg.stamp_ns)
                self._odom.clear()
                self._sim_odom = -1
                self._odom_origin = None
                self._last_sweep_seq = self._last_frame_stamp = -1
                self._last_ack = None
                self._now_ns = msg.stamp_ns
            self._now_ns = max(self._now_ns, msg.stamp_ns)
            stamp = self._robot_ns(msg.stamp_ns)
            if self._odom and stamp < self._odom[-1].stamp_ns and msg.stamp_ns >= self._sim_odom:
                self._odom.clear()   # the robot's clock stepped back: older stamps mislead
            if msg.stamp_ns > self._sim_odom:
                self._sim_odom = msg.stamp_ns
                self._odom.append(Odometry(stamp, self._own_odometry(msg.pose), msg.v_mps,
                                           msg.omega_rps))

    def _own_odometry(self, sim_pose: Pose) -> Pose:
        """The robot's odometry for the simulator's ``sim_pose`` (see the module's doc)."""
        if not self._odometry_at_zero:
            return sim_pose
        if self._odom_origin is None:
            self._odom_origin = sim_pose
            log.info("odometry starts at zero here (the simulator's %s)",
                     ", ".join(f"{v:.3f}" for v in sim_pose))
        x, y, th = between(self._odom_origin, sim_pose).tolist()
        return (x, y, th)

    def _image(self, msg: SimImage) -> None:
        if msg.stamp_ns == self._last_frame_stamp:
            return  # re-sent with its step
        if msg.encoding != "mono8":
            self.counters["unsupported_images"] += 1
            return
        self._last_frame_stamp = msg.stamp_ns
        image = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width)
        K = np.array([[msg.fx, 0.0, msg.cx], [0.0, msg.fy, msg.cy], [0.0, 0.0, 1.0]])
        if self._on_frame is not None:
            self._on_frame(Frame(self._robot_ns(msg.stamp_ns), image, K))

    def _lidar(self, msg: SimLidar) -> None:
        with self._lock:
            self._now_ns = max(self._now_ns, msg.stamp_ns)
            self._lockstep = msg.lockstep
            repeat = msg.seq == self._last_sweep_seq
            if not repeat:
                self._last_sweep_seq = msg.seq
            last_ack = self._last_ack
        if repeat:
            self.counters["repeated_sweeps"] += 1
            if last_ack is not None and last_ack.step == msg.seq:
                self.bus.publish(keys.sim_ack(self.robot_id), last_ack, block=True)
            return
        if self._on_sweep is not None:
            self._on_sweep(Sweep(self._robot_ns(msg.stamp_ns), msg.angle_min_rad,
                                 msg.angle_increment_rad, msg.range_min_mm, msg.range_max_mm,
                                 msg.ranges_mm,
                                 step=msg.seq if msg.lockstep else None))


class _SimCamera:
    def __init__(self, backend: SimBackend) -> None:
        self.backend = backend

    def start(self, on_frame: Callable[[Frame], None]) -> None:
        self.backend.start_camera(on_frame)


def sim_backend(bus: Bus, robot_id: str, clock_steps: Sequence[tuple[float, float]] = (),
                odometry_at_zero: bool = False) -> Backend:
    """The Backend of ``robot_id`` in a running simulator reachable on ``bus``."""
    b = SimBackend(bus, robot_id, clock_steps, odometry_at_zero)
    return Backend(lidar=b, base=b, camera=_SimCamera(b), now_ns=b.now_ns, sync=b,
                   monotonic_ns=b.sim_ns,
                   close=b.close, counters=lambda: dict(b.counters))
