"""The simulator backend: the robot's LIDAR, base and camera are messages on ``mrslam/sim/...``.

The simulator publishes, per step, the clock, then this robot's frames, odometry and sweep (see
``schemas.sim``); all arrive on one Zenoh link in that order. The robot's clock is the latest
simulation time seen. A sweep the simulator re-sends (its ack was late or lost) is not handed to
the agent again; the step's ack is re-sent instead.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter, deque
from collections.abc import Callable

import numpy as np

from robot_agent.backend import Backend, Frame, Odometry, Sweep
from schemas import SimClock, SimImage, SimLidar, SimMotorCommand, SimOdometry, SimStepAck, keys
from schemas.bus import Bus

log = logging.getLogger(__name__)


class SimBackend:
    """LIDAR source, base, camera and step sync of one simulated robot."""

    def __init__(self, bus: Bus, robot_id: str) -> None:
        self.bus = bus
        self.robot_id = robot_id
        self._lock = threading.Lock()
        self._now_ns = 0
        self._lockstep = False
        self._odom: deque[Odometry] = deque(maxlen=64)
        self._last_sweep_seq = -1
        self._last_frame_stamp = -1
        self._last_ack: SimStepAck | None = None
        self._ack_seq = 0
        self._motor_seq = 0
        self._on_sweep: Callable[[Sweep], None] | None = None
        self._on_frame: Callable[[Frame], None] | None = None
        self.counters: Counter[str] = Counter()
        bus.subscribe(keys.SIM_CLOCK, SimClock, self._clock)
        bus.subscribe(keys.sim_odom(robot_id), SimOdometry, self._odometry)
        bus.subscribe(keys.sim_image(robot_id), SimImage, self._image)
        bus.subscribe(keys.sim_lidar(robot_id), SimLidar, self._lidar)

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
        return self._now_ns

    def lockstep(self) -> bool:  # StepSync
        return self._lockstep

    def ack(self, step: int, command: tuple[float, float]) -> None:  # StepSync
        with self._lock:
            self._ack_seq += 1
            msg = SimStepAck(robot_id=self.robot_id, seq=self._ack_seq, stamp_ns=self._now_ns,
                             step=step, v_mps=command[0], omega_rps=command[1])
            self._last_ack = msg
        self.bus.publish(keys.sim_ack(self.robot_id), msg, block=True)

    # -- bus callbacks ----------------------------------------------------------------------
    def _mine(self, robot_id: str) -> bool:
        if robot_id != self.robot_id:
            self.counters["foreign_messages"] += 1
            return False
        return True

    def _clock(self, key: str, msg: SimClock) -> None:
        with self._lock:
            self._now_ns = max(self._now_ns, msg.stamp_ns)
            self._lockstep = msg.lockstep

    def _odometry(self, key: str, msg: SimOdometry) -> None:
        if self._mine(msg.robot_id):
            with self._lock:
                if not self._odom or msg.stamp_ns > self._odom[-1].stamp_ns:
                    self._odom.append(Odometry(msg.stamp_ns, msg.pose, msg.v_mps,
                                               msg.omega_rps))

    def _image(self, key: str, msg: SimImage) -> None:
        if not self._mine(msg.robot_id) or msg.stamp_ns <= self._last_frame_stamp:
            return
        if msg.encoding != "mono8":
            self.counters["unsupported_images"] += 1
            return
        self._last_frame_stamp = msg.stamp_ns
        image = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width)
        K = np.array([[msg.fx, 0.0, msg.cx], [0.0, msg.fy, msg.cy], [0.0, 0.0, 1.0]])
        if self._on_frame is not None:
            self._on_frame(Frame(msg.stamp_ns, image, K))

    def _lidar(self, key: str, msg: SimLidar) -> None:
        if not self._mine(msg.robot_id):
            return
        with self._lock:
            self._now_ns = max(self._now_ns, msg.stamp_ns)
            repeat = msg.seq <= self._last_sweep_seq
            if not repeat:
                self._last_sweep_seq = msg.seq
            last_ack = self._last_ack
        if repeat:
            self.counters["repeated_sweeps"] += 1
            if last_ack is not None and last_ack.step == msg.seq:
                self.bus.publish(keys.sim_ack(self.robot_id), last_ack, block=True)
            return
        if self._on_sweep is not None:
            self._on_sweep(Sweep(msg.stamp_ns, msg.angle_min_rad, msg.angle_increment_rad,
                                 msg.range_min_mm, msg.range_max_mm, msg.ranges_mm,
                                 step=msg.seq if self._lockstep else None))


class _SimCamera:
    def __init__(self, backend: SimBackend) -> None:
        self.backend = backend

    def start(self, on_frame: Callable[[Frame], None]) -> None:
        self.backend.start_camera(on_frame)


def sim_backend(bus: Bus, robot_id: str) -> Backend:
    """The Backend of ``robot_id`` in a running simulator reachable on ``bus``."""
    b = SimBackend(bus, robot_id)
    return Backend(lidar=b, base=b, camera=_SimCamera(b), now_ns=b.now_ns, sync=b,
                   counters=lambda: dict(b.counters))
