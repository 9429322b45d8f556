"""A RealSense depth camera (D435i and kin) as the tower's frame source, through
``pyrealsense2`` (an optional package: ``pip install pyrealsense2``; not needed by a LIDAR robot).

``open()`` starts the depth stream (z16) at ``width`` × ``height`` and ``fps`` and reads the
stream's intrinsics (``fx``, ``cx``) and the device's depth scale; ``grab()`` waits for the
next frame and returns it as a ``DepthFrame`` stamped on the host clock. RealSense stamps frames
in milliseconds in one of three domains; only the system-time domain is the host's clock, so a
frame in another domain is stamped with its arrival on the host (a few tens of ms after its
exposure; the tower waits for the camera to settle at each heading, so the robot's motion in
between is what the stamp can be off by). Errors are ``DepthCameraError`` (a ``RuntimeError``,
which the tower's source retries on).

Not tested against a device here: the tests drive the tower with synthetic frames.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from robot_agent.drivers.tower import DepthFrame

log = logging.getLogger(__name__)


class DepthCameraError(RuntimeError):
    """The depth camera cannot be used (package missing, no device, no frames)."""

    user_error = True


def _rs() -> Any:
    try:
        import pyrealsense2 as rs  # type: ignore[import-not-found]
    except ImportError:
        raise DepthCameraError("the depth camera needs the pyrealsense2 package: "
                               "pip install pyrealsense2") from None
    return rs


class RealSenseDepth:
    def __init__(self, width: int = 848, height: int = 480, fps: int = 30,
                 serial_number: str | None = None, timeout_s: float = 1.0) -> None:
        self.width, self.height, self.fps = width, height, fps
        self.serial_number = serial_number
        self.timeout_ms = max(1, round(timeout_s * 1000))
        self.fx = self.cx = float("nan")
        self.scale_m = 0.001
        self._pipe: Any = None

    def open(self) -> None:
        rs = _rs()
        cfg = rs.config()
        if self.serial_number:
            cfg.enable_device(self.serial_number)
        cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        pipe = rs.pipeline()
        try:
            profile = pipe.start(cfg)
            intr = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
            self.fx, self.cx = float(intr.fx), float(intr.ppx)
            self.scale_m = float(profile.get_device().first_depth_sensor().get_depth_scale())
        except RuntimeError as e:
            raise DepthCameraError(f"depth camera {self.serial_number or '(any)'}: {e}") from None
        self._pipe = pipe
        log.info("depth camera: %d x %d at %d Hz, fx %.1f px, cx %.1f px, scale %g m",
                 self.width, self.height, self.fps, self.fx, self.cx, self.scale_m)

    def grab(self) -> DepthFrame:
        if self._pipe is None:
            raise DepthCameraError("the depth camera is not open")
        rs = _rs()
        try:
            frames = self._pipe.wait_for_frames(self.timeout_ms)
        except RuntimeError as e:
            raise DepthCameraError(f"depth camera: no frame in {self.timeout_ms} ms: {e}"
                                   ) from None
        arrived = time.time_ns()
        depth = frames.get_depth_frame()
        image = np.asanyarray(depth.get_data()).copy()
        stamp = arrived
        if depth.get_frame_timestamp_domain() == rs.timestamp_domain.system_time:
            stamp = round(depth.get_timestamp() * 1e6)
        return DepthFrame(image, stamp, self.scale_m)

    def close(self) -> None:
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            try:
                pipe.stop()
            except RuntimeError as e:
                log.debug("depth camera: stop: %s", e)
