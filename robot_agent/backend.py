"""What the agent needs from a robot: a LIDAR, a base, a camera (and, in a lockstep simulator,
a way to acknowledge steps). Hardware drivers and the simulator backend implement these."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from schemas.messages import ranges_from_mm

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class Sweep:
    """One LIDAR sweep; beam ``i`` at ``angle_min_rad + i * angle_increment_rad``."""

    stamp_ns: int
    angle_min_rad: float
    angle_increment_rad: float
    range_min_mm: int
    range_max_mm: int
    ranges_mm: bytes                 # uint16 little-endian, 0 = no return
    step: int | None = None          # the simulator's step (lockstep only)

    def polar(self) -> tuple[np.ndarray, np.ndarray]:
        """Ranges [m] (inf: no return) and beam angles [rad]."""
        ranges = ranges_from_mm(self.ranges_mm)
        return ranges, self.angle_min_rad + self.angle_increment_rad * np.arange(len(ranges))


@dataclass(frozen=True)
class Odometry:
    stamp_ns: int
    pose: Pose                       # wheel-odometry pose (drifts)
    v_mps: float = 0.0
    omega_rps: float = 0.0


@dataclass(frozen=True)
class Frame:
    stamp_ns: int
    image: np.ndarray                # (H, W) uint8 grayscale
    K: np.ndarray                    # (3, 3) intrinsics
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))


class LidarSource(Protocol):
    def start(self, on_sweep: Callable[[Sweep], None]) -> None:
        """Call ``on_sweep`` for every sweep, in order, from any thread."""


class Base(Protocol):
    def odometry_at(self, stamp_ns: int) -> Odometry | None:
        """Wheel odometry at ``stamp_ns`` (None when none is known yet)."""

    def set_velocity(self, v_mps: float, omega_rps: float) -> None:
        """Drive at body velocity (v, ω) until told otherwise."""


class Camera(Protocol):
    def start(self, on_frame: Callable[[Frame], None]) -> None:
        """Call ``on_frame`` for every frame, from any thread."""


class StepSync(Protocol):
    """A lockstep simulator waits for every agent to acknowledge each step."""

    def lockstep(self) -> bool:
        """True while the simulator runs in lockstep."""

    def ack(self, step: int, command: tuple[float, float]) -> None:
        """Report ``step`` handled; ``command`` is the (v, ω) to hold from now on."""


@dataclass
class Backend:
    lidar: LidarSource
    base: Base
    camera: Camera | None
    now_ns: Callable[[], int]        # the robot's clock (simulation time in simulation)
    sync: StepSync | None = None
    #: a clock that never steps, for time-to-live (the robot's clock may: NTP, a boot in 1970)
    monotonic_ns: Callable[[], int] = time.monotonic_ns
    close: Callable[[], None] = lambda: None
    counters: Callable[[], dict[str, int]] = dict
