"""What a narrow sensor showed around its robot in the last seconds (``ObstacleMemory``)."""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class ObstacleMemory:
    """What a narrow sensor (a depth camera, turned or fixed) showed around its robot in the
    last seconds, in the map frame: the reactive layer avoids a wall behind or beside the
    robot that its latest scan, looking elsewhere, does not show."""

    def __init__(self) -> None:
        self.views: deque[tuple[int, F64]] = deque()

    def around(self, stamp_ns: int, pose: F64, points_robot: F64, keep_s: float) -> F64:
        """The latest scan's points and the kept ones, in the robot frame at ``pose``."""
        c, s = math.cos(pose[2]), math.sin(pose[2])
        R = np.array([[c, -s], [s, c]])
        while self.views and (self.views[0][0] < stamp_ns - keep_s * 1e9
                              or self.views[0][0] > stamp_ns):   # too old, or a clock step
            self.views.popleft()
        older = [v for _, v in self.views]
        self.views.append((stamp_ns, points_robot @ R.T + pose[:2]))
        if not older:
            return points_robot
        kept = (np.concatenate(older) - pose[:2]) @ R
        return np.concatenate([points_robot, kept])
