"""The pose-graph back-end, split in two so that several robots can later share one problem:

- ``RobotTrajectory``: one robot's keys ``gtsam.symbol(c, block·2³² + k)`` and the factors it
  added (kept,
  so they can be re-inserted into another graph), its prior factor and that prior's index in
  the graph that currently holds it (so the prior can be removed when robots are joined);
- ``PoseGraph``: a GTSAM problem optimised incrementally with ISAM2, holding any number of
  trajectories; it knows nothing about scans.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.scan_match import pose2, prior_factor

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


#: symbol letters of the first robots; robot n uses ``KEY_CHARS[n % 52]`` in key block ``n // 52``
KEY_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"
#: keyframes per robot: a key's index is ``block << KEY_INDEX_BITS | k`` (gtsam has 56 bits)
KEY_INDEX_BITS = 32
_SYMBOL_INDEX_BITS = 56   # gtsam.Symbol: the character above 56 bits of index
#: ``PoseGraph.poses`` reads keys one by one (about 4.5 µs each) rather than the whole
#: estimate (about 0.7 µs per key in the graph) when they are at most this share of the graph
FEW_KEYS_SHARE = 1 / 6


def robot_key_space(n: int) -> tuple[str, int]:
    """The symbol letter and key block of the ``n``-th robot (0-based): room for 52 · 2²⁴
    robots of 2³² keyframes each in gtsam's 56-bit symbol index."""
    if not 0 <= n < len(KEY_CHARS) << (56 - KEY_INDEX_BITS):
        raise ValueError(f"no graph keys left for robot number {n}")
    return KEY_CHARS[n % len(KEY_CHARS)], n // len(KEY_CHARS)


class GraphError(RuntimeError):
    """The optimiser rejected an update (e.g. a key without any constraint)."""


@dataclass
class FactorRecord:
    """A factor a robot added, what it is, and its index in the graph holding it (or None)."""

    factor: gtsam.NoiseModelFactor
    kind: str  # "prior", "match", "odometry", "loop", "heading", "sweep"
    index: int | None = None


@dataclass
class RobotTrajectory:
    """One robot's keyframe keys and factors, independent of the graph that optimises them."""

    robot_char: str
    block: int = 0           # key block (see ``robot_key_space``)
    n_keys: int = 0
    factors: list[FactorRecord] = field(default_factory=list)
    prior: FactorRecord | None = None

    def __post_init__(self) -> None:
        if len(self.robot_char) != 1:
            raise ValueError(f"robot char must be one character, got {self.robot_char!r}")

    def key(self, k: int) -> int:
        if not 0 <= k < 1 << KEY_INDEX_BITS:
            raise GraphError(f"keyframe index {k} is outside a robot's key range")
        return self._base() | k

    def all_keys(self) -> list[int]:
        base = self._base()
        return [base | k for k in range(self.n_keys)]

    def _base(self) -> int:
        """``gtsam.symbol(robot_char, block << KEY_INDEX_BITS)``, computed as GTSAM does
        (the character in the top 8 bits, the index below) without a call into it; GTSAM's
        own answer (or error) where the character or block does not fit."""
        c, j = ord(self.robot_char), self.block << KEY_INDEX_BITS
        if c > 127 or j < 0 or j >> _SYMBOL_INDEX_BITS:
            return int(gtsam.symbol(self.robot_char, j))
        return c << _SYMBOL_INDEX_BITS | j

    def prior_pose(self) -> F64:
        """Where the prior pins the first key (the origin of the robot's own map frame)."""
        if self.prior is None:
            return np.zeros(3)
        p = self.prior.factor.prior()  # type: ignore[attr-defined]
        return np.array([p.x(), p.y(), p.theta()])

    def records(self, kind: str | None = None) -> list[FactorRecord]:
        return [r for r in self.factors if kind is None or r.kind == kind]


class PoseGraph:
    """An ISAM2 problem over Pose2 keys. ``add`` returns the indices of the new factors."""

    def __init__(self, relinearize_threshold: float = 0.01) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = 1
        self._params = params
        self._threshold = relinearize_threshold
        self.isam = gtsam.ISAM2(params)
        self._estimate: gtsam.Values | None = None
        self.n_updates = 0
        self.n_values = 0        # keys inserted so far

    # -- snapshots (pickle): ISAM2 itself cannot be pickled, its factors and values can -----
    def __getstate__(self) -> dict[str, Any]:
        fg = self.isam.getFactorsUnsafe()
        return {"threshold": self._threshold, "n_updates": self.n_updates,
                "factors": [fg.at(i) if fg.exists(i) else None for i in range(fg.size())],
                "values": self.isam.getLinearizationPoint()}

    def __setstate__(self, state: dict[str, Any]) -> None:
        """A new ISAM2 problem with every factor in its old slot (indices held elsewhere stay
        valid), linearised where the old one was; empty slots are filled and emptied again."""
        self.__init__(state["threshold"])  # type: ignore[misc]
        values: gtsam.Values = state["values"]
        graph, holes = gtsam.NonlinearFactorGraph(), []
        keys = values.keys()
        for i, f in enumerate(state["factors"]):
            if f is None:
                holes.append(i)
                f = gtsam.PriorFactorPose2(keys[0], values.atPose2(keys[0]),
                                           gtsam.noiseModel.Isotropic.Sigma(3, 1e3))
            graph.add(f)
        if graph.size():
            self.isam.update(graph, values)
        if holes:
            self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), holes)
        self.n_updates = state["n_updates"]
        self.n_values = int(values.size())

    def add(self, factors: list[gtsam.NonlinearFactor], new_values: dict[int, F64],
            remove: list[int] | None = None) -> list[int]:
        graph = gtsam.NonlinearFactorGraph()
        for f in factors:
            graph.add(f)
        values = gtsam.Values()
        for key, T in new_values.items():
            values.insert(key, pose2(T))
        try:
            res = self.isam.update(graph, values, list(remove or []))
        except RuntimeError as e:
            raise GraphError(f"ISAM2 update failed: {e}") from e
        self._estimate = None
        self.n_updates += 1
        self.n_values += len(new_values)
        return [int(i) for i in res.getNewFactorsIndices()]

    def iterate(self, n: int) -> None:
        """Extra ISAM2 steps without new factors (after a loop closure moved many poses)."""
        for _ in range(n):
            self.isam.update()
        self._estimate = None

    def remove(self, indices: list[int]) -> None:
        if indices:
            self.add([], {}, remove=indices)

    def estimate(self) -> gtsam.Values:
        if self._estimate is None:
            self._estimate = self.isam.calculateEstimate()
        return self._estimate

    def pose(self, key: int) -> F64:
        p = self.isam.calculateEstimatePose2(key)
        return np.array([p.x(), p.y(), p.theta()])

    def poses(self, keys: list[int]) -> F64:
        """Current estimates (N, 3) of ``keys``, in that order."""
        if not keys:
            return np.zeros((0, 3))
        if self._estimate is None and len(keys) <= FEW_KEYS_SHARE * self.n_values:
            # a few keys (the local map's) without the whole estimate: the same retraction
            # of each key's linearisation point by its delta, for these keys only
            return np.array([self.pose(k) for k in keys], dtype=np.float64).reshape(-1, 3)
        est = self.estimate()
        all_keys = np.asarray(est.keys(), dtype=np.uint64)
        table = gtsam.utilities.extractPose2(est)
        pos = np.searchsorted(all_keys, np.asarray(keys, dtype=np.uint64))
        return np.asarray(table[pos], dtype=np.float64)

    def marginal_covariance(self, key: int) -> F64:
        """The 3×3 marginal covariance of pose ``key`` (in its own frame: x, y, θ)."""
        return np.asarray(self.isam.marginalCovariance(key), np.float64)

    def factor(self, index: int) -> gtsam.NonlinearFactor:
        return self.isam.getFactorsUnsafe().at(index)


def start_trajectory(graph: PoseGraph, trajectory: RobotTrajectory, T_map_first: F64,
                     prior_sigmas: F64) -> None:
    """Insert a trajectory's first key with its prior."""
    key = trajectory.key(0)
    f = prior_factor(key, T_map_first, prior_sigmas)
    (idx,) = graph.add([f], {key: T_map_first})
    trajectory.prior = FactorRecord(f, "prior", idx)
    trajectory.factors.append(trajectory.prior)
    trajectory.n_keys = 1


def extend_trajectory(graph: PoseGraph, trajectory: RobotTrajectory,
                      factor: gtsam.NoiseModelFactor, kind: str, T_map_new: F64) -> int:
    """Add the next key of a trajectory, constrained by ``factor`` to the previous key."""
    key = trajectory.key(trajectory.n_keys)
    (idx,) = graph.add([factor], {key: T_map_new})
    trajectory.factors.append(FactorRecord(factor, kind, idx))
    trajectory.n_keys += 1
    return idx


def add_constraint(graph: PoseGraph, trajectory: RobotTrajectory,
                   factor: gtsam.NoiseModelFactor, kind: str) -> FactorRecord:
    """Add a factor between existing keys (a loop closure)."""
    (idx,) = graph.add([factor], {})
    rec = FactorRecord(factor, kind, idx)
    trajectory.factors.append(rec)
    return rec


def drop_constraint(graph: PoseGraph, trajectory: RobotTrajectory, rec: FactorRecord) -> None:
    """Remove a factor a trajectory added (e.g. a loop closure found inconsistent)."""
    if rec.index is not None:
        graph.remove([rec.index])
        rec.index = None
    trajectory.factors.remove(rec)
