"""Stuck detection (little progress over a time window) and a recovery manoeuvre."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from server.control.geometry import Twist


class StampOrderError(ValueError):
    """A stamp earlier than the previous one (the message names both)."""


class StuckDetector:
    """Stuck when the robot moved less than ``min_progress_m`` (straight-line displacement)
    between the pose ``window_s`` ago and now. Feed it only while the robot should be driving;
    :meth:`reset` on a new goal and after a recovery."""

    def __init__(self, window_s: float = 8.0, min_progress_m: float = 0.15) -> None:
        if not (window_s > 0 and min_progress_m > 0):
            raise ValueError("window_s and min_progress_m must be > 0")
        self.window_s = window_s
        self.min_progress_m = min_progress_m
        self._history: deque[tuple[float, float, float]] = deque()

    def reset(self) -> None:
        self._history.clear()

    def update(self, stamp_s: float, pose: ArrayLike) -> bool:
        """Add a pose (x, y, θ) at ``stamp_s`` [s]; True when stuck."""
        x, y = (float(v) for v in np.asarray(pose, np.float64).reshape(-1)[:2])
        if not (math.isfinite(stamp_s) and math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"non-finite stamp or pose: {stamp_s}, ({x}, {y})")
        h = self._history
        if h and stamp_s < h[-1][0]:
            raise StampOrderError(f"stamp {stamp_s:.3f} s is earlier than the previous "
                                  f"{h[-1][0]:.3f} s")
        h.append((stamp_s, x, y))
        # Keep the newest sample at least window_s old as the reference.
        while len(h) >= 2 and h[1][0] <= stamp_s - self.window_s:
            h.popleft()
        t0, x0, y0 = h[0]
        if stamp_s - t0 < self.window_s:
            return False
        return math.hypot(x - x0, y - y0) < self.min_progress_m


@dataclass(frozen=True)
class RecoveryParams:
    backup_speed_mps: float = 0.1
    backup_s: float = 2.0
    omega_rps: float = 1.0
    rotate_rad: float = math.pi / 2
    # Back up only when no scan point lies behind the robot within this distance.
    rear_clearance_m: float = 0.35
    rear_half_width_m: float = 0.2


class Recovery:
    """Back up (when the rear is clear), then turn on the spot towards the more open side."""

    def __init__(self, params: RecoveryParams | None = None) -> None:
        self.params = params or RecoveryParams()
        self._phases: list[tuple[float, Twist]] = []   # (end stamp, command)

    @property
    def active(self) -> bool:
        return bool(self._phases)

    def start(self, stamp_s: float, points_robot_xy: ArrayLike) -> None:
        """Plan the manoeuvre from the latest scan points (robot frame, metres)."""
        p = self.params
        pts = np.asarray(points_robot_xy, np.float64).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        behind = pts[(pts[:, 0] < 0) & (np.abs(pts[:, 1]) < p.rear_half_width_m)]
        rear_clear = not np.any(-behind[:, 0] < p.rear_clearance_m)
        left, right = pts[pts[:, 1] > 0], pts[pts[:, 1] < 0]

        def openness(q: np.ndarray) -> float:
            return float(np.mean(np.hypot(q[:, 0], q[:, 1]))) if len(q) else math.inf

        side = 1.0 if openness(left) >= openness(right) else -1.0
        t = stamp_s
        self._phases = []
        if rear_clear:
            t += p.backup_s
            self._phases.append((t, Twist(-p.backup_speed_mps, 0.0)))
        t += p.rotate_rad / p.omega_rps
        self._phases.append((t, Twist(0.0, side * p.omega_rps)))

    def command(self, stamp_s: float) -> Twist | None:
        """The recovery command at ``stamp_s``; None once the manoeuvre is over."""
        while self._phases and stamp_s >= self._phases[0][0]:
            self._phases.pop(0)
        return self._phases[0][1] if self._phases else None
