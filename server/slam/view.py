"""What passes between ``RobotSlam`` and a sensor model (``server.slam.sensor``): the robot's
state as the model may read it (``SlamView``), what the model makes of a matched scan
(``Placement``), and the counters both add to (``SlamStats``).

The view is read-only by contract: a sensor model adds factors to the graph and edges to the
loop closer's path graph through the functions of ``backend`` and ``loop_closure``, and counts
in ``stats``; the pipeline's own state (the anchor, the local map) it only reads. Keeping this
surface small is what lets a sensor's handling live outside the pipeline.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from server.slam.backend import PoseGraph, RobotTrajectory
from server.slam.frontend import FrontendMatch, MatchKind
from server.slam.icp import PointMap
from server.slam.keyframes import Keyframe
from server.slam.loop_closure import LoopCloser
from server.slam.scan import ScanPoints
from server.slam.scan_poses import Anchor

F64 = NDArray[np.float64]


@dataclass
class SlamStats:
    """Counters: scans accepted, keyframes, how each scan was matched, loop closures kept and
    taken out again."""

    scans: int = 0
    keyframes: int = 0
    matches: dict[str, int] = field(default_factory=lambda: {k.value: 0 for k in MatchKind})
    loop_closures: int = 0
    loop_closures_removed: int = 0
    reused: int = 0   # scans re-anchored on a keyframe instead of adding one (``reuse``)
    heading_ties: int = 0   # keyframes whose heading square walls tied (``square_walls``)
    sweeps: int = 0   # whole scans of a turning camera matched (``sweep``)
    sweep_shift_m: float = 0.0   # how far the latest one's match moved the pose from the guess
    guided_sweeps: int = 0   # of those, matched against a wide teammate's map (``narrow``)
    smoothing_resets: int = 0   # narrow matches whose average strayed from them (``narrow``)


@dataclass(frozen=True)
class Placement:
    """A scan and its pose, as the sensor model hands them to the keyframe step.

    ``scan`` is the scan given, or one the model assembled from several (a turning camera's
    views taken standing still: ``whole``), which then stands for it and becomes a new
    keyframe whatever the robot's motion. ``matched_to`` is the keyframe such a scan was
    matched against instead of the local map: the factor from the anchor then carries the
    odometry only, and the model adds the match's own factor (``SensorModel.on_keyframe``).
    """

    scan: ScanPoints
    match: FrontendMatch
    whole: bool = False
    matched_to: int | None = None


class SlamView(Protocol):
    """The parts of a robot's SLAM a sensor model may read (``RobotSlam`` is one)."""

    @property
    def graph(self) -> PoseGraph: ...

    @property
    def trajectory(self) -> RobotTrajectory: ...

    @property
    def keyframes(self) -> list[Keyframe]: ...

    @property
    def stats(self) -> SlamStats: ...

    @property
    def loops(self) -> LoopCloser: ...

    @property
    def guides(self) -> Sequence[SlamView]:
        """Teammates sharing this graph (set by the server before each scan)."""
        ...

    @property
    def narrow(self) -> bool:
        """Whether its latest scan was a narrow sensor's."""
        ...

    @property
    def local_map(self) -> PointMap | None:
        """The map the latest scan was matched against (map frame)."""
        ...

    @property
    def velocity(self) -> F64:
        """The motion (x, y, θ) from the scan before the latest to the latest, robot frame."""
        ...

    @property
    def anchor(self) -> Anchor:
        """The keyframe the robot's pose is kept relative to, and its pose."""
        ...

    def keyframe_poses(self) -> F64:
        """Optimised poses (K, 3) of all keyframes, map frame."""
        ...
