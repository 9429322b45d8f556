"""Camera: a capture device (fake, fed with rendered tag images) -> frames -> ArUco sightings."""

from __future__ import annotations

import json
import math
import queue
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from robot_agent.aruco import TagDetector
from robot_agent.backend import Frame
from robot_agent.drivers.camera import (
    CalibrationError,
    OpenCVCamera,
    load_calibration,
    parse_calibration,
)
from schemas.tags import CameraMount, TagLayout
from sim.simulator import SimParams, Simulator
from sim.world import World
from tests.waiting import within

LAYOUT, MOUNT = TagLayout(), CameraMount()


class FakeCapture:
    """A ``cv2.VideoCapture`` stand-in: BGR frames at ``fps``, blocking in ``grab`` like V4L2."""

    def __init__(self, images: list[np.ndarray], fps: float = 30.0, fail_after: int = -1) -> None:
        self.images, self.period = images, 1.0 / fps
        self.grabs = self.retrieves = 0
        self.fail_after = fail_after
        self.released = False
        self._next = time.monotonic()

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        return True

    def grab(self) -> bool:
        time.sleep(max(self._next - time.monotonic(), 0.0))
        self._next = max(self._next + self.period, time.monotonic())
        self.grabs += 1
        return self.fail_after < 0 or self.grabs <= self.fail_after

    def retrieve(self) -> tuple[bool, np.ndarray]:
        self.retrieves += 1
        image = self.images[(self.grabs - 1) % len(self.images)]
        return True, cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)

    def release(self) -> None:
        self.released = True


def rendered_frame() -> tuple[np.ndarray, np.ndarray, float]:
    """A frame of r1's camera with r2's front tag 1.4 m ahead; (image, K, true range)."""
    world = World.from_shapes("empty", "test", [np.array([[50, 50], [51, 50], [51, 51],
                                                          [50, 51.0]])], [])
    d = 1.4
    pose = (MOUNT.x_m + d + LAYOUT.mast_half_width_m, 0.1, math.pi)
    sim = Simulator(world, {"r1": (0.0, 0.0, 0.0), "r2": pose}, SimParams(), seed=1)
    frame = sim.sense().frames["r1"]
    rel = frame.relatives[0][2]
    return frame.image, sim.p.camera.camera.K, math.hypot(rel[0], rel[1])


def test_frames_are_rate_limited_calibrated_and_show_the_tags(tmp_path: Path) -> None:
    image, K, true_range = rendered_frame()
    calib = tmp_path / "camera.yaml"      # the ROS camera_info layout
    calib.write_text(yaml.safe_dump({
        "image_width": image.shape[1], "image_height": image.shape[0],
        "camera_matrix": {"rows": 3, "cols": 3, "data": K.reshape(-1).tolist()},
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5}}))
    cap = FakeCapture([image], fps=30.0)
    cam = OpenCVCamera(0, load_calibration(calib), rate_hz=5.0, capture_factory=lambda d: cap)
    frames: queue.Queue[Frame] = queue.Queue()
    t0 = time.monotonic()
    cam.start(frames.put)
    time.sleep(1.0)
    cam.close()
    n = frames.qsize()
    elapsed = time.monotonic() - t0
    assert 4 <= n <= 7 and cap.grabs >= 5 * n        # every frame grabbed, few decoded
    assert cap.retrieves == n and cap.released and elapsed < 2.0
    frame = frames.get()
    assert frame.image.dtype == np.uint8 and frame.image.ndim == 2
    assert np.array_equal(frame.K, K) and frame.stamp_ns > 0
    found = TagDetector(LAYOUT, MOUNT).detect(frame.image, frame.K, "r1", frame.dist)
    s = next(s for s in found.sightings if s.robot_id == "r2")
    assert abs(s.range_m - true_range) < 0.03


def test_a_failing_device_is_reopened_and_a_wrong_size_is_dropped(tmp_path: Path) -> None:
    image, K, _ = rendered_frame()
    caps: list[FakeCapture] = []
    def factory(device: int | str) -> FakeCapture:
        caps.append(FakeCapture([image], fps=100.0, fail_after=5))
        return caps[-1]
    calib = parse_calibration({"K": K.tolist(), "dist": [0.0] * 5, "image_width": 320,
                               "image_height": 240})
    cam = OpenCVCamera("/dev/video0", calib, rate_hz=50.0, reconnect_s=0.05, max_failures=3,
                       capture_factory=factory)
    cam.start(lambda f: None)
    try:
        assert within(lambda: len(caps) >= 2, 3.0)
        assert within(lambda: cam.counters["size_mismatch"] >= 1, 1.0)
    finally:
        cam.close()
    assert cam.counters["camera_CameraError"] >= 1 and cam.counters["frames"] == 0


@pytest.mark.parametrize("content, match", [
    ({"dist": [0.0] * 5}, "no K"),
    ({"K": [1, 2, 3]}, "9 finite numbers"),
    ({"K": [[500, 0, 320], [0, 500, 240], [1, 0, 1]]}, "not a camera matrix"),
    ({"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "dist": [0.1, 0.2, 0.3]}, "dist needs"),
    ([1, 2], "mapping"),
])
def test_bad_calibration_files_are_typed_errors(tmp_path: Path, content: object,
                                                match: str) -> None:
    path = tmp_path / "c.json"
    path.write_text(json.dumps(content))
    with pytest.raises(CalibrationError, match=match):
        load_calibration(path)
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "missing.yaml")
