"""Messages between the simulator and the agents' sim backend (``mrslam/sim/...``).

These stand in for hardware: a raw LIDAR sweep, wheel odometry, a camera frame, and a motor
command. The simulator also publishes its clock and the ground truth; in lockstep mode it waits
for a ``SimStepAck`` from every agent before advancing.

One simulation step is one LIDAR period. For step ``k`` the simulator publishes, in this order,
``SimClock`` (``step = k``), then per robot any ``SimImage`` frames, ``SimOdometry`` and
``SimLidar`` (both with ``seq = k`` and ``stamp_ns`` = the simulation time of step ``k``), then
``SimGroundTruth`` (``seq = k``). All stamps are simulation time [ns] from 0 at step 0.
Zenoh keeps the order of one session's messages, but a receiver with one subscriber per key
sees them on different threads; a backend that needs a robot's messages in order subscribes to
``mrslam/sim/robot/<id>/*`` once.
In lockstep mode the world moves from step ``k`` to ``k + 1`` only after every robot's agent
has sent ``SimStepAck(step = k)``, and the motor command carried by that ack (if any) is the
one applied; ``SimMotorCommand`` drives the robots in real-time mode.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.messages import LidarSweep, Message, fail
from schemas.types import Pose2, RobotId, Seq


class SimClock(Message, kw_only=True):
    """Simulated time is ``stamp_ns``; ``step`` counts physics steps of ``dt_ns``."""

    step: Seq
    dt_ns: Annotated[int, msgspec.Meta(gt=0, le=10**10)]
    lockstep: bool = False
    real_time_factor: Annotated[float, msgspec.Meta(ge=0.0, le=1e6)] = 1.0


class SimLidar(LidarSweep, kw_only=True):
    """A raw simulated LIDAR sweep, before the agent pairs it with odometry.

    ``seq`` is the simulation step; with ``lockstep`` the simulator waits for a
    ``SimStepAck(step=seq)`` from this robot's agent before it advances.
    """

    lockstep: bool = False


class SimOdometry(Message, kw_only=True):
    """Wheel odometry as the robot's encoders would report it (it drifts)."""

    robot_id: RobotId
    pose: Pose2
    v_mps: Annotated[float, msgspec.Meta(ge=-10.0, le=10.0)] = 0.0
    omega_rps: Annotated[float, msgspec.Meta(ge=-50.0, le=50.0)] = 0.0


class SimImage(Message, kw_only=True):
    """A grayscale camera frame with the pinhole intrinsics it was rendered with (no lens
    distortion). ``seq`` counts this robot's frames (``TrueRelative.image_seq`` refers to it)."""

    robot_id: RobotId
    width: Annotated[int, msgspec.Meta(ge=1, le=8192)]
    height: Annotated[int, msgspec.Meta(ge=1, le=8192)]
    fx: Annotated[float, msgspec.Meta(gt=0.0, le=1e6)]
    fy: Annotated[float, msgspec.Meta(gt=0.0, le=1e6)]
    cx: Annotated[float, msgspec.Meta(ge=-1e6, le=1e6)]
    cy: Annotated[float, msgspec.Meta(ge=-1e6, le=1e6)]
    encoding: Literal["mono8", "png"] = "mono8"
    data: bytes

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.encoding == "mono8" and len(self.data) != self.width * self.height:
            fail("data", f"{len(self.data)} bytes, expected {self.width * self.height} for mono8")


class SimMotorCommand(Message, kw_only=True):
    robot_id: RobotId
    v_mps: Annotated[float, msgspec.Meta(ge=-5.0, le=5.0)]
    omega_rps: Annotated[float, msgspec.Meta(ge=-20.0, le=20.0)]


class SimStepAck(Message, kw_only=True):
    """An agent has handled every sensor message of ``step`` (lockstep mode).

    ``v_mps``/``omega_rps`` is the motor command to hold from this step on (None: keep the
    previous one), so that the command a lockstep run applies never depends on timing.
    """

    robot_id: RobotId
    step: Seq
    v_mps: Annotated[float, msgspec.Meta(ge=-5.0, le=5.0)] | None = None
    omega_rps: Annotated[float, msgspec.Meta(ge=-20.0, le=20.0)] | None = None


class TruePose(msgspec.Struct, kw_only=True):
    robot_id: RobotId
    pose: Pose2
    collisions: Seq = 0
    distance_m: Annotated[float, msgspec.Meta(ge=0.0, le=1e7)] = 0.0


class TrueRelative(msgspec.Struct, kw_only=True):
    """Ground truth of one rendered tag view: the observed robot in the observer's frame."""

    observer_id: RobotId
    observed_id: RobotId
    tag_id: Annotated[int, msgspec.Meta(ge=0, le=4095)]
    relative_pose: Pose2
    image_seq: Seq
    spurious: Annotated[str, msgspec.Meta(
        max_length=16, description="'' for a true view; else how it was falsified: "
        "'id' (another robot's tag), 'pose' (drawn ≥ 1 m or ≥ 30° off), 'occluded' "
        "(seen through a wall)")] = ""


class SimGroundTruth(Message, kw_only=True):
    poses: Annotated[list[TruePose], msgspec.Meta(max_length=256)]
    relatives: Annotated[list[TrueRelative], msgspec.Meta(max_length=4096)] = (
        msgspec.field(default_factory=list))
    world: Annotated[str, msgspec.Meta(max_length=1024)] = ""
