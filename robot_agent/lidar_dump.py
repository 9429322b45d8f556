"""``mrslam lidar-dump``: print a few sweeps of a LIDAR, to check a new device.

One line per sweep: ``stamp_ns n angle_0 range_0 … angle_n-1 range_n-1`` with angles in
radians in the robot frame (counter-clockwise, fixed beams from −π) and ranges in metres,
``inf`` for no return.
"""

from __future__ import annotations

import queue
import sys
from typing import TextIO

from robot_agent.backend import Sweep
from robot_agent.drivers.rplidar import LidarTimeout, RplidarSource


def format_sweep(sweep: Sweep) -> str:
    ranges, angles = sweep.polar()
    pairs = " ".join(f"{a:.5f} {r:.3f}" for a, r in zip(angles, ranges, strict=True))
    return f"{sweep.stamp_ns} {len(ranges)} {pairs}"


def run(port: str, scans: int, baud: int = 115200, beams: int = 360,
        timeout_s: float = 10.0, out: TextIO | None = None) -> int:
    """Print ``scans`` sweeps from the RPLIDAR on ``port``; returns how many were printed.

    Raises ``LidarTimeout`` naming the last problem when no sweep arrives within
    ``timeout_s``.
    """
    out = out or sys.stdout
    sweeps: queue.Queue[Sweep] = queue.Queue()
    source = RplidarSource(port, baud, beams=beams, reconnect_s=0.5)
    source.start(sweeps.put)
    try:
        for _ in range(scans):
            try:
                sweep = sweeps.get(timeout=timeout_s)
            except queue.Empty:
                why = source.last_error or "the device sent no complete revolution"
                raise LidarTimeout(f"no sweep from {port} within {timeout_s} s: {why}") from None
            out.write(format_sweep(sweep) + "\n")
            out.flush()
    finally:
        source.close()
    return scans
