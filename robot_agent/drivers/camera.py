"""A camera through OpenCV's ``VideoCapture``: grayscale frames with calibrated intrinsics.

The calibration file (YAML or JSON) gives the intrinsics either as ``K`` (3×3, or 9 numbers
row by row) and ``dist`` (OpenCV's k1 k2 p1 p2 [k3 …]), or in the ROS ``camera_info`` layout
(``camera_matrix.data``, ``distortion_coefficients.data``); ``image_width``/``image_height``,
when present, must match the frames (intrinsics of another resolution would put every tag in
the wrong place). The camera is grabbed at its own rate so frames are never stale, and only
every ``1/rate_hz`` is a frame decoded and handed on.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from robot_agent.backend import Frame

log = logging.getLogger(__name__)


class CameraError(Exception):
    """The camera or its calibration cannot be used."""

    user_error = True


class CalibrationError(CameraError):
    """A calibration file that is missing, unreadable or does not fit the frames."""


@dataclass(frozen=True)
class Calibration:
    K: np.ndarray                      # (3, 3)
    dist: np.ndarray                   # (n,)
    width: int | None = None
    height: int | None = None


def _matrix(value: Any, name: str) -> np.ndarray:
    if isinstance(value, dict):
        value = value.get("data")
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CalibrationError(f"{name}: not a list of numbers") from None
    return a


def parse_calibration(data: Any, source: str = "calibration") -> Calibration:
    if not isinstance(data, dict):
        raise CalibrationError(f"{source}: expected a mapping with K and dist")
    k_raw = data.get("K", data.get("camera_matrix"))
    if k_raw is None:
        raise CalibrationError(f"{source}: no K (or camera_matrix)")
    K = _matrix(k_raw, f"{source}: K")
    if K.size != 9 or not np.all(np.isfinite(K)):
        raise CalibrationError(f"{source}: K needs 9 finite numbers, got {K.size}")
    K = K.reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise CalibrationError(f"{source}: K is not a camera matrix (fx, fy > 0, last row "
                               "0 0 1)")
    dist = _matrix(data.get("dist", data.get("distortion_coefficients", [])), f"{source}: dist")
    if dist.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise CalibrationError(f"{source}: dist needs 4, 5, 8, 12 or 14 finite numbers, "
                               f"got {dist.size}")
    w, h = data.get("image_width"), data.get("image_height")
    return Calibration(K, dist if dist.size else np.zeros(5),
                       int(w) if w is not None else None, int(h) if h is not None else None)


def load_calibration(path: str | Path) -> Calibration:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise CalibrationError(f"cannot read calibration {p}: {e.strerror}") from None
    try:
        data = json.loads(text) if p.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as e:
        raise CalibrationError(f"{p}: not valid {p.suffix.lstrip('.') or 'YAML'}: {e}") from None
    return parse_calibration(data, str(p))


class OpenCVCamera:
    """The agent's ``Camera``: rate-limited grayscale frames from a ``VideoCapture``."""

    def __init__(self, device: int | str, calibration: Calibration, rate_hz: float = 5.0,
                 width: int | None = None, height: int | None = None,
                 reconnect_s: float = 1.0, max_failures: int = 10,
                 capture_factory: Callable[..., Any] = cv2.VideoCapture) -> None:
        self.device, self.calibration = device, calibration
        self.period_s = 1.0 / rate_hz
        self.width = width or calibration.width
        self.height = height or calibration.height
        self.reconnect_s, self.max_failures = reconnect_s, max_failures
        self.capture_factory = capture_factory
        self.counters: Counter[str] = Counter()
        self.last_error = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, on_frame: Callable[[Frame], None]) -> None:
        self._thread = threading.Thread(target=self._run, args=(on_frame,), daemon=True,
                                        name="camera")
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)

    def _run(self, on_frame: Callable[[Frame], None]) -> None:
        while not self._stop.is_set():
            cap = None
            try:
                cap = self._open()
                self._stream(cap, on_frame)
            except CameraError as e:
                self.counters[f"camera_{type(e).__name__}"] += 1
                if str(e) != self.last_error:
                    log.warning("camera: %s; retrying every %g s", e, self.reconnect_s)
                    self.last_error = str(e)
            finally:
                if cap is not None:
                    cap.release()
            self._stop.wait(self.reconnect_s)

    def _open(self) -> Any:
        cap = self.capture_factory(self.device)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"cannot open camera {self.device!r}")
        if self.width and self.height:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        return cap

    def _stream(self, cap: Any, on_frame: Callable[[Frame], None]) -> None:
        failures = 0
        next_frame = 0.0
        while not self._stop.is_set():
            if not cap.grab():
                failures += 1
                self.counters["grab_failures"] += 1
                if failures >= self.max_failures:
                    raise CameraError(f"camera {self.device!r}: {failures} grabs failed")
                time.sleep(0.01)
                continue
            failures = 0
            stamp_ns = time.time_ns()
            now = time.monotonic()
            if now < next_frame:
                continue            # grabbed (keeps the driver's queue fresh), not decoded
            next_frame = now + self.period_s
            ok, image = cap.retrieve()
            if not ok or image is None:
                self.counters["decode_failures"] += 1
                continue
            frame = self._frame(image, stamp_ns)
            if frame is not None:
                on_frame(frame)
                self.counters["frames"] += 1

    def _frame(self, image: np.ndarray, stamp_ns: int) -> Frame | None:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        c = self.calibration
        h, w = gray.shape[:2]
        if (c.width, c.height) != (None, None) and (w, h) != (c.width, c.height):
            self.counters["size_mismatch"] += 1
            if self.counters["size_mismatch"] == 1:
                log.warning("camera %r gives %dx%d frames, its calibration is for %sx%s: "
                            "frames dropped", self.device, w, h, c.width, c.height)
            return None
        return Frame(stamp_ns, np.ascontiguousarray(gray, np.uint8), c.K, c.dist)
