"""A 360° pseudo-scan from a depth camera turned to several headings (e.g. 0°, 90°, 180°, 270°).

For each depth image, the middle row is one fan of beams. With the pinhole model, column ``u``
looks along ``α = atan2(cx − u, fx)`` left of the optical axis (image x grows to the right, the
robot frame turns counter-clockwise), and the depth camera measures ``z``, the distance along the
optical axis, so the range along the ray is ``r = z / cos α``. The camera heading ``yaw`` turns
the fan into the robot frame (``θ = yaw + α``), and the fans are merged onto fixed beams from −π
(nearest beam; the nearest obstacle wins where fans overlap). Depth 0 (no measurement) and
ranges beyond ``max_range_m`` are no-returns: depth cameras are noisy far away (the D435i's
error grows with z²), so the scan stops at a trusted range.

Views taken while the robot moves (a camera on a turning tower takes a second or more for a
full turn) carry ``origin``: the robot's pose at the view's capture in the robot frame of the
scan's reference instant (from odometry: ``between(pose_ref, pose_capture)``). Each reading
becomes a point ``r·(cos θ, sin θ)``, is moved by that pose, and is binned by its angle and
distance from the reference robot's origin; a no-return keeps its direction, turned by the
pose's heading. The default ``(0, 0, 0)`` leaves the fan as it was.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robot_agent.backend import Sweep
from robot_agent.drivers.beams import to_beams
from schemas.messages import quantise_ranges_mm


class DepthScanError(ValueError):
    """A depth image that cannot become part of a pseudo-scan."""

    user_error = True


@dataclass(frozen=True)
class DepthView:
    yaw_rad: float                 # heading of the optical axis in the robot frame
    depth: np.ndarray              # (H, W) depth along the optical axis, in units of ``scale_m``
    scale_m: float = 1.0           # metres per depth unit (RealSense z16: 0.001)
    # robot pose (x [m], y [m], θ [rad]) at capture, in the robot frame of the reference instant
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)


def fan(view: DepthView, fx: float, cx: float, rows: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(angles [rad] in the robot frame, ranges [m], inf = no measurement) of a view's middle row.

    ``rows`` > 1 takes the median of that many middle rows (ignoring zeros) against speckle.
    """
    d = np.asarray(view.depth)
    if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 2:
        raise DepthScanError(f"depth image of shape {d.shape}, expected (H, W)")
    h = d.shape[0]
    top = max(h // 2 - rows // 2, 0)
    band = d[top:top + rows].astype(np.float64) * view.scale_m
    band[~np.isfinite(band) | (band <= 0)] = np.nan
    with np.errstate(all="ignore"):
        z = band[0] if rows == 1 else np.nanmedian(band, axis=0)
    alpha = np.arctan2(cx - np.arange(d.shape[1]), fx)
    r = z / np.cos(alpha)
    r[~np.isfinite(r)] = np.inf
    theta = view.yaw_rad + alpha
    ox, oy, oth = (float(v) for v in view.origin)
    if (ox, oy, oth) == (0.0, 0.0, 0.0):
        return theta, r
    if not all(math.isfinite(v) for v in (ox, oy, oth)):
        raise DepthScanError(f"view origin {view.origin} is not finite")
    hit = np.isfinite(r)
    t = theta + oth
    with np.errstate(invalid="ignore"):
        x = np.where(hit, r * np.cos(t) + ox, np.inf)
        y = np.where(hit, r * np.sin(t) + oy, np.inf)
    out_theta = np.where(hit, np.arctan2(y, x), t)
    out_r = np.where(hit, np.hypot(x, y), np.inf)
    return out_theta, out_r


def merge_fans(fans: Sequence[tuple[np.ndarray, np.ndarray]], beams: int, max_range_m: float,
               min_range_m: float = 0.0) -> np.ndarray:
    """Ranges [m] on ``beams`` beams from −π (inf = no return), nearest reading per beam
    (``beams.to_beams``: a column without a reading in range still covers its beam)."""
    if not fans:
        return np.full(beams, np.inf)
    angles = np.concatenate([a for a, _ in fans])
    ranges = np.concatenate([r for _, r in fans])
    ok = np.isfinite(ranges) & (ranges <= max_range_m) & (ranges >= min_range_m)
    return to_beams(angles, np.where(ok, ranges, np.inf), beams)


def pseudo_scan(views: Sequence[DepthView], fx: float, cx: float, stamp_ns: int,
                beams: int = 360, max_range_m: float = 3.0, min_range_m: float = 0.2,
                rows: int = 1) -> Sweep:
    """The views merged into one fixed-beam sweep (range_max = ``max_range_m``)."""
    if not views:
        raise DepthScanError("no depth views")
    ranges = merge_fans([fan(v, fx, cx, rows) for v in views], beams, max_range_m, min_range_m)
    return Sweep(stamp_ns=stamp_ns, angle_min_rad=-math.pi, angle_increment_rad=2 * math.pi
                 / beams, range_min_mm=round(min_range_m * 1000),
                 range_max_mm=round(max_range_m * 1000),
                 ranges_mm=quantise_ranges_mm(ranges, min_range_m, max_range_m))
