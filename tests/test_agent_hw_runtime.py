"""The agent with the hardware backend on loopback: a pty RPLIDAR, a pty microcontroller, a real
Zenoh router played by the test as the server (which goes away and comes back)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from robot_agent import runtime
from robot_agent.config import AgentConfig
from robot_agent.drivers.fakes.base import FakeMicrocontroller
from robot_agent.drivers.fakes.rplidar import FakeRplidar, wall_room_mm
from schemas import Scan, VelocityCommand, keys
from schemas.bus import Bus
from tests.conftest import ROOT
from tests.waiting import within

HEAVY = ["gtsam", "open3d", "skimage", "scipy", "server", "factors", "sim", "matplotlib"]


def test_hardware_modules_do_not_import_server_libraries() -> None:
    code = ("import json, sys\n"
            "import robot_agent.runtime, robot_agent.hardware, robot_agent.lidar_dump\n"
            "import robot_agent.drivers.depth_scan\n"
            f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=60, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_hardware_config_needs_a_calibration_for_the_camera(tmp_path: Path) -> None:
    from robot_agent.drivers.camera import CalibrationError
    from robot_agent.hardware import hardware_backend

    cfg = AgentConfig.model_validate({"backend": "hardware", "hardware": {
        "base": {"port": str(tmp_path / "none")}}})
    with pytest.raises(CalibrationError, match="calibration is required"):
        hardware_backend(cfg.hardware)


class HardwareAgent:
    """The agent with the hardware backend on a pty RPLIDAR and microcontroller, run in a
    thread until ``stop`` is set; ``result`` gets its summary (or the error it raised)."""

    def __init__(self, tmp_path: Path, endpoint: str) -> None:
        self.lidar = FakeRplidar(tmp_path / "rplidar", wall_room_mm(2000.0))
        self.mcu = FakeMicrocontroller(tmp_path / "base")
        self.stop = threading.Event()
        self.result: dict[str, Any] = {}
        overrides = {"robot_id": "r1", "backend": "hardware", "bus": {"connect": [endpoint]},
                     "hardware": {"lidar": {"port": str(self.lidar.link), "reconnect_s": 0.2},
                                  "base": {"port": str(self.mcu.link), "reconnect_s": 0.2},
                                  "camera": {"enabled": False}}}

        def agent() -> None:
            try:
                self.result["summary"] = runtime.run(None, overrides, self.stop)
            except Exception as e:  # surfaced by the test
                self.result["error"] = e

        self.thread = threading.Thread(target=agent)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=20)
        self.lidar.close()
        self.mcu.close()


def test_scans_commands_server_loss_and_return(tmp_path: Path, endpoint: str) -> None:
    hw = HardwareAgent(tmp_path, endpoint)
    mcu, result, thread = hw.mcu, hw.result, hw.thread
    scans: list[Scan] = []
    server = Bus.open("router", listen=[endpoint])
    try:
        token = server.declare_alive(keys.SERVER_ALIVE)
        server.subscribe(keys.robot_scan("r1"), Scan, lambda k, m: scans.append(m))
        thread.start()
        assert within(lambda: len(scans) >= 3, 10.0), result
        s = scans[-1]
        assert s.n_beams == 360 and s.range_max_mm == 12000 and len(s.odom_pose) == 3

        def command(v: float, seq: int) -> None:
            server.publish(keys.robot_cmd_vel("r1"), VelocityCommand(
                robot_id="r1", seq=seq, stamp_ns=time.time_ns(), v_mps=v, omega_rps=0.0,
                ttl_s=5.0))
        for k in range(8):
            command(0.2, k)
            time.sleep(0.1)
        assert mcu.speed[0] > 0 and mcu.speed[0] == mcu.speed[1]
        assert within(lambda: scans[-1].odom_pose[0] > 0.05, 2.0)   # odometry in the scans

        # the server dies: its session (and liveliness token) closes, commands stop
        command(0.2, 99)
        t_gone = time.monotonic()
        del token
        server.close()
        assert within(lambda: mcu.stopped_since() is not None, 1.0)
        assert mcu.stopped_since() - t_gone <= 0.5   # type: ignore[operator]

        # it comes back on the same endpoint: the agent's session reconnects
        n = len(scans)
        server = Bus.open("router", listen=[endpoint])
        server.declare_alive(keys.SERVER_ALIVE)
        server.subscribe(keys.robot_scan("r1"), Scan, lambda k, m: scans.append(m))
        assert within(lambda: len(scans) > n + 2, 20.0), "no scans after the server returned"
    finally:
        hw.close()
        server.close()
    assert "error" not in result, result.get("error")
    summary = result["summary"]
    assert summary["scans_sent"] >= 5 and summary["commands_received"] >= 8
    assert summary["server_losses"] >= 1


def test_a_robot_clock_stepping_back_does_not_keep_the_motors_running(
        tmp_path: Path, endpoint: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Commands hold for their time-to-live on a clock that never steps: with the robot's
    own clock set back an hour (NTP) right after the last command, the watchdog still fires
    (on the robot's clock its deadline would lie an hour ahead) and the base stops."""
    offset = {"ns": 0}
    real_time_ns = time.time_ns
    monkeypatch.setattr(time, "time_ns", lambda: real_time_ns() + offset["ns"])
    hw = HardwareAgent(tmp_path, endpoint)
    mcu, result, thread = hw.mcu, hw.result, hw.thread
    scans: list[Scan] = []
    with Bus.open("router", listen=[endpoint]) as server:
        try:
            server.declare_alive(keys.SERVER_ALIVE)
            server.subscribe(keys.robot_scan("r1"), Scan, lambda k, m: scans.append(m))
            thread.start()
            assert within(lambda: len(scans) >= 3, 10.0), result
            for k in range(10):   # answer scans as the server does: with their own stamps
                server.publish(keys.robot_cmd_vel("r1"), VelocityCommand(
                    robot_id="r1", seq=k, stamp_ns=scans[-1].stamp_ns, v_mps=0.2,
                    omega_rps=0.0, ttl_s=0.5))
                time.sleep(0.1)
            assert within(lambda: mcu.speed[0] > 0, 2.0)
            offset["ns"] = -3600 * 1_000_000_000
            t_last = time.monotonic()
            assert within(lambda: mcu.stopped_since() is not None, 3.0), \
                "the motors kept running after the robot's clock stepped back"
            assert mcu.stopped_since() - t_last <= 1.0   # type: ignore[operator]
            time.sleep(1.0)   # the base driver's own hold stops it too; the watchdog must fire
        finally:
            hw.close()
    assert "error" not in result, result.get("error")
    assert result["summary"]["watchdog_timeouts"] == 1, str(result["summary"])
