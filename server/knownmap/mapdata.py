"""A known map: keyframes at fixed poses in one frame, as a previous mission left them.

A mission's map is its team's keyframes (scans with their points, normals and free space) at
their optimised poses, in the team's frame. ``KnownMap`` holds them in one list, whichever
robot made them; ``harvest`` takes them from a team at the end of a mission, and ``map_slam``
makes them a pose graph of their own for the next one: every keyframe held where the map put
it by a tight prior, so that robots placed in the map are tied to it and the map does not move
under them. No I/O here (``server.runtime.mapstore`` reads and writes it).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.scan_match import prior_factor
from server.slam import RobotSlam
from server.slam.backend import FactorRecord, start_trajectory
from server.slam.keyframes import Keyframe
from server.slam.scan_poses import Anchor

F64 = NDArray[np.float64]

#: how firmly a known map's keyframes are held where the map put them (σ, m and degrees): the
#: map is the reference robots are placed in, not something they bend
MAP_SIGMA_M, MAP_SIGMA_DEG = 0.01, 0.1


@dataclass
class KnownMap:
    """Keyframes at their poses (K, 3) in the map's frame, and where each came from."""

    keyframes: list[Keyframe]
    poses: F64
    sources: list[str]              # the robot that made each keyframe
    resolution_m: float
    anchor: str = ""                # the robot whose first pose is the map frame's origin
    missions: int = 1               # missions that made or kept this map
    notes: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.keyframes)

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 3)
        if len(self.poses) != len(self.keyframes) or len(self.sources) != len(self.keyframes):
            raise ValueError(f"a known map of {len(self.keyframes)} keyframes with "
                             f"{len(self.poses)} poses and {len(self.sources)} sources")

    @property
    def stamps_ns(self) -> NDArray[np.int64]:
        return np.array([kf.stamp_ns for kf in self.keyframes], dtype=np.int64)


def map_slam(known: KnownMap, slam: RobotSlam) -> RobotSlam:
    """``slam`` (fresh, with its own graph keys) made to hold the known map: keyframe k at
    its map pose, each held there by a prior (σ ``MAP_SIGMA_M``, ``MAP_SIGMA_DEG``). The
    first prior is the trajectory's own (the team's anchor keeps it when graphs are
    joined); the others are factors of kind ``map``, which joining keeps too."""
    if not len(known):
        raise ValueError("a known map without keyframes")
    sigmas = np.array([MAP_SIGMA_M, MAP_SIGMA_M, math.radians(MAP_SIGMA_DEG)])
    tr = slam.trajectory
    start_trajectory(slam.graph, tr, known.poses[0], sigmas)
    factors: list[gtsam.NoiseModelFactor] = []
    values: dict[int, F64] = {}
    for k in range(1, len(known)):
        key = tr.key(k)
        factors.append(prior_factor(key, known.poses[k], sigmas))
        values[key] = known.poses[k]
    if factors:
        indices = slam.graph.add(list[gtsam.NonlinearFactor](factors), values)
        tr.factors += [FactorRecord(f, "map", i) for f, i in zip(factors, indices, strict=True)]
    tr.n_keys = len(known)
    slam.keyframes = [_renumbered(kf, k) for k, kf in enumerate(known.keyframes)]
    slam.stats.keyframes = len(known)
    slam.anchor = Anchor(0, known.poses[0].copy())
    slam.rebind(slam.graph)
    return slam


def _renumbered(kf: Keyframe, index: int) -> Keyframe:
    if kf.index == index:
        return kf
    return Keyframe(index, kf.stamp_ns, kf.T_odom_robot, kf.matchable, kf.render)


def harvest(parts: Iterable[tuple[list[str], list[Keyframe], F64]], resolution_m: float,
            anchor: str, missions: int, notes: dict[str, str] | None = None) -> KnownMap:
    """A known map of the keyframes given, part by part: (each keyframe's source, keyframes,
    poses in the map frame). A source names the mission and robot that made the keyframe
    (``"2:r1"``)."""
    kfs: list[Keyframe] = []
    poses: list[F64] = []
    sources: list[str] = []
    for names, keyframes, at in parts:
        at = np.asarray(at, dtype=np.float64).reshape(-1, 3)
        for name, kf, T in zip(names, keyframes, at, strict=True):
            kfs.append(_renumbered(kf, len(kfs)))
            poses.append(T)
            sources.append(name)
    return KnownMap(kfs, np.array(poses).reshape(-1, 3), sources, resolution_m, anchor,
                    missions, dict(notes or {}))
