"""The camera tower as the agent's range sensor: pseudo-scans streamed from a thread, the tower
opened again after it is lost, a camera that fails retried, and the hardware backend's wiring
(``hardware.range_sensor: depth-tower``). The controller is the pty fake of
``test_agent_hw_tower``; frames are rendered from the rotor's true heading in a known room."""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from robot_agent.backend import Odometry, Sweep
from robot_agent.config import AgentConfig
from robot_agent.drivers.fakes.tower import FakeTowerController
from robot_agent.drivers.tower import DepthFrame, Tower, TowerSource
from robot_agent.hardware import depth_tower
from tests.test_agent_hw_tower import CX, FX, SPR, TRIGGER, H, W, wall_errors, wall_hit
from tests.waiting import within

POSE = (0.3, 0.1, 0.2)


class RoomCamera:
    """A depth camera in the test room, on whichever fake controller is current; ``broken``
    makes ``open`` fail as an unplugged camera does."""

    def __init__(self) -> None:
        self.fake: FakeTowerController | None = None
        self.broken = False
        self.opens = self.closes = 0
        self.fx = self.cx = float("nan")

    def open(self) -> None:
        self.opens += 1
        if self.broken:
            raise RuntimeError("No device connected")
        self.fx, self.cx = FX, CX

    def close(self) -> None:
        self.closes += 1

    def grab(self) -> DepthFrame:
        fake = self.fake
        assert fake is not None
        x, y, th = POSE
        yaw = 2 * math.pi * (fake.physical - fake.trigger_step) / fake.steps_per_rev
        alpha = np.arctan2(CX - np.arange(W), FX)
        z = wall_hit(x, y, th + yaw + alpha) * np.cos(alpha)
        return DepthFrame(np.tile(np.rint(z * 1000), (H, 1)).astype(np.uint16), time.time_ns())


class Sweeps:
    def __init__(self) -> None:
        self.got: list[Sweep] = []
        self.lock = threading.Lock()

    def __call__(self, sweep: Sweep) -> None:
        with self.lock:
            self.got.append(sweep)

    def count(self) -> int:
        with self.lock:
            return len(self.got)


def fake_at(link: Path) -> FakeTowerController:
    return FakeTowerController(link, steps_per_rev=SPR, trigger_step=TRIGGER)


def make_source(link: Path, cam: RoomCamera, reconnect_s: float = 0.2) -> TowerSource:
    tower = Tower(str(link), cam.grab, lambda t_ns: POSE, fx=FX, cx=CX, steps_per_rev=SPR,
                  settle_s=0.01, beams=720, keepalive_s=0.05, link_timeout_s=0.5)
    return TowerSource(tower, reconnect_s, cam.open, cam.close)


def test_the_source_streams_pseudo_scans_that_lie_on_the_walls(tmp_path: Path) -> None:
    cam = RoomCamera()
    cam.fake = fake_at(tmp_path / "tower")
    src = make_source(tmp_path / "tower", cam)
    got = Sweeps()
    try:
        src.start(got)
        assert within(lambda: got.count() >= 3, 20.0), src.all_counters()
    finally:
        src.close()
        cam.fake.close()
    stamps = [s.stamp_ns for s in got.got]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    for s in got.got[:3]:
        err = wall_errors(s, POSE)
        assert len(err) > 0.7 * 720 and err.max() < 0.03
    c = src.all_counters()
    assert c["connects"] == 1 and c["sweeps"] >= 3 and cam.opens == 1
    assert cam.closes == 1                       # closed with the source


def test_a_tower_lost_is_opened_again_when_it_comes_back(tmp_path: Path,
                                                         caplog: pytest.LogCaptureFixture
                                                         ) -> None:
    caplog.set_level(logging.INFO)
    link = tmp_path / "tower"
    cam = RoomCamera()
    cam.fake = fake_at(link)
    src = make_source(link, cam)
    got = Sweeps()
    try:
        src.start(got)
        assert within(lambda: got.count() >= 1, 20.0)
        cam.fake.close()                          # unplugged: the port and its link vanish
        assert within(lambda: any(k.startswith("tower_Tower") for k in src.counters), 10.0)
        assert not src.connected.is_set()
        before = got.count()
        time.sleep(0.6)                           # retries meanwhile find no port
        assert got.count() <= before + 1
        cam.fake = fake_at(link)                  # plugged in again under the same name
        assert within(lambda: got.count() >= before + 2, 20.0), src.all_counters()
    finally:
        src.close()
        cam.fake.close()
    assert src.counters["connects"] >= 2
    assert "retrying every 0.2 s" in caplog.text and "back" in caplog.text
    assert caplog.text.count("retrying every") <= 3   # each new problem once, not every retry
    err = wall_errors(got.got[-1], POSE)
    assert err.max() < 0.03                        # homed again: headings are right


def test_a_camera_that_fails_to_open_is_retried_and_counted(tmp_path: Path) -> None:
    link = tmp_path / "tower"
    cam = RoomCamera()
    cam.broken = True
    cam.fake = fake_at(link)
    src = make_source(link, cam, reconnect_s=0.05)
    got = Sweeps()
    try:
        src.start(got)
        assert within(lambda: src.counters["tower_RuntimeError"] >= 3, 10.0)
        assert got.count() == 0 and cam.fake.homes == 0    # no camera: the tower waits
        cam.broken = False
        assert within(lambda: got.count() >= 1, 20.0)
    finally:
        src.close()
        cam.fake.close()


class StillBase:
    """A base whose odometry is known from its first call on."""

    def __init__(self) -> None:
        self.asked: list[int] = []

    def odometry_at(self, stamp_ns: int) -> Odometry | None:
        self.asked.append(stamp_ns)
        return Odometry(stamp_ns, POSE)

    def set_velocity(self, v_mps: float, omega_rps: float) -> None:
        pass


def test_the_backend_wiring_takes_the_intrinsics_when_the_camera_opens(tmp_path: Path) -> None:
    cfg = AgentConfig.model_validate({"backend": "hardware", "hardware": {
        "range_sensor": "depth-tower",
        "tower": {"port": str(tmp_path / "tower"), "steps_per_rev": SPR, "settle_s": 0.01,
                  "beams": 720, "reconnect_s": 0.2}}})
    assert cfg.hardware.range_sensor == "depth-tower"
    cam = RoomCamera()
    cam.fake = fake_at(tmp_path / "tower")
    base = StillBase()
    src = depth_tower(cfg.hardware.tower, base, frames=cam)
    assert math.isnan(src.tower.fx)               # not known before the camera is open
    got = Sweeps()
    try:
        src.start(got)
        assert within(lambda: got.count() >= 1, 20.0), src.all_counters()
    finally:
        src.close()
        cam.fake.close()
    assert src.tower.fx == FX and src.tower.cx == CX
    assert len(base.asked) >= 4                    # every view placed by the base's odometry
    assert wall_errors(got.got[0], POSE).max() < 0.03


def test_an_unknown_range_sensor_is_refused() -> None:
    with pytest.raises(ValueError, match="range_sensor"):
        AgentConfig.model_validate({"hardware": {"range_sensor": "sonar"}})


def test_the_realsense_driver_names_the_package_it_needs() -> None:
    from robot_agent.drivers.realsense import DepthCameraError, RealSenseDepth

    try:
        import pyrealsense2  # type: ignore[import-not-found]  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("pyrealsense2 is installed: the error for a missing package cannot occur")
    cam = RealSenseDepth()
    with pytest.raises(DepthCameraError, match="pip install pyrealsense2"):
        cam.open()
    with pytest.raises(DepthCameraError, match="not open"):
        cam.grab()
    cam.close()                                     # closing what never opened is fine
    assert isinstance(DepthCameraError("x"), RuntimeError)     # the tower's source retries it


