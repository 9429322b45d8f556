"""Where the robot is and was, relative to its keyframes.

The robot's pose is kept relative to one keyframe, its ``Anchor``, and so is each scan's
(``ScanPoses``): a pose kept so follows the graph when a loop closure or a merge moves that
keyframe, without being touched. A sighting of another robot is placed by ``ScanPoses.at``:
the pose at the sighting's stamp, interpolated between the scans around it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, pose_distance
from server.slam.stamped import StampedRows

F64 = NDArray[np.float64]


def _identity() -> F64:
    return np.zeros(3)


@dataclass
class Anchor:
    """The keyframe the robot's pose is kept relative to (the newest, or one re-used where
    the robot passes again), its pose in the map frame (the graph's estimate, read again
    whenever the graph moves), the robot relative to it, and where the robot was relative to
    it when it was taken up (a re-used keyframe may face elsewhere)."""

    index: int
    T_map_kf: F64
    T_kf_robot: F64 = field(default_factory=_identity)
    T_kf_taken_up: F64 = field(default_factory=_identity)

    @classmethod
    def taken_up(cls, index: int, T_map_kf: F64, T_map_robot: F64) -> Anchor:
        """Keyframe ``index`` as the anchor of a robot at ``T_map_robot``."""
        T_kf_robot = between(T_map_kf, T_map_robot)
        return cls(index, T_map_kf, T_kf_robot, T_kf_robot.copy())

    @property
    def T_map_robot(self) -> F64:
        return compose(self.T_map_kf, self.T_kf_robot)

    def moved(self) -> tuple[float, float]:
        """Distance [m] and turn [rad] since the anchor was taken up."""
        return pose_distance(between(self.T_kf_taken_up, self.T_kf_robot))


@dataclass(frozen=True)
class ScanPose:
    """Where a scan was, relative to the keyframe it was matched after."""

    stamp_ns: int
    keyframe: int
    T_kf_robot: F64


class ScanPoses:
    """Every scan's stamp, keyframe and pose relative to it, in the order added (stamps do
    not go back)."""

    def __init__(self) -> None:
        self._rows = StampedRows(3)

    def __len__(self) -> int:
        return len(self._rows)

    def append(self, stamp_ns: int, keyframe: int, T_kf_robot: F64) -> None:
        self._rows.append(stamp_ns, T_kf_robot, tag=keyframe)

    def in_map(self, T_map_kf: F64) -> tuple[NDArray[np.int64], F64]:
        """Stamps [ns] and map-frame poses (N, 3) of every scan, the keyframes at
        ``T_map_kf`` (K, 3)."""
        rows = self._rows
        if not len(rows):
            return rows.stamps.copy(), np.zeros((0, 3))
        return rows.stamps.copy(), compose(T_map_kf[rows.tags], rows.values)

    def at(self, stamp_ns: int, T_map_kfs: Callable[[list[int]], F64],
           tolerance_ns: int = 150_000_000) -> tuple[int, F64] | None:
        """Where the robot was at ``stamp_ns``: a keyframe index and the robot's pose relative
        to that keyframe, interpolated between the scans around that instant
        (``T_map_kfs(indices)`` gives keyframes' poses). None when no scan is close enough,
        and — later than the newest scan — until the next scan is in (a robot turning at
        1.5 rad/s turns 9° in one scan period: the pose of the scan before is not the pose
        at the sighting). Before the first scan, the first within ``tolerance_ns``; across a
        gap in the scans (dropped while the server was behind) wider than 2 ×
        ``tolerance_ns``, the nearest within a third of it."""
        rows = self._rows
        if not len(rows):
            return None
        stamps = rows.stamps
        i = int(np.searchsorted(stamps, stamp_ns, side="left"))
        if i < len(rows) and stamps[i] == stamp_ns:
            return int(rows.tags[i]), rows.values[i].copy()
        if i == len(rows):
            return None
        if i == 0:
            if int(stamps[0]) - stamp_ns > tolerance_ns:
                return None
            return int(rows.tags[0]), rows.values[0].copy()
        a, b = ScanPose(*rows.row(i - 1)), ScanPose(*rows.row(i))
        if b.stamp_ns - a.stamp_ns > 2 * tolerance_ns:
            near = a if stamp_ns - a.stamp_ns <= b.stamp_ns - stamp_ns else b
            if abs(near.stamp_ns - stamp_ns) > tolerance_ns // 3:
                return None
            return near.keyframe, near.T_kf_robot.copy()
        f = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        Xa, Xb = T_map_kfs([a.keyframe, b.keyframe])
        Pa, Pb = compose(Xa, a.T_kf_robot), compose(Xb, b.T_kf_robot)
        step = between(Pa, Pb)
        return a.keyframe, compose(a.T_kf_robot, step * f)
