"""A simulated base holds a command only for its time-to-live, as the motor firmware does.

An agent that hangs (here: a real agent process stopped with SIGSTOP) must leave its robot
standing within the time-to-live, in real-time and in lockstep mode, and the robot must drive
again once the agent's commands resume.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from schemas import Scan, SimGroundTruth, VelocityCommand, keys
from schemas.bus import Bus
from sim import process
from sim.config import DEFAULT_SCENARIOS
from sim.robot import DriveLimits
from sim.simulator import SimParams, Simulator
from sim.world import World
from tests.conftest import ROOT
from tests.waiting import within

V_MPS = 0.3
TTL_S = 0.5
STEP_S = 0.1
# the farthest a robot at V_MPS goes once its last command was given: the time-to-live, one
# step of rounding, and braking at the drive's deceleration limit
BOUND_M = V_MPS * (TTL_S + STEP_S) + V_MPS**2 / (2 * DriveLimits().accel_max_mps2)


def open_floor() -> World:
    wall = np.array([[30.0, -30.0], [31.0, -30.0], [31.0, 30.0], [30.0, 30.0]])
    return World.from_shapes("open", "test", [wall], [])


def test_a_command_lapses_after_its_time_to_live_and_a_new_one_drives_again(
        caplog: pytest.LogCaptureFixture) -> None:
    params = SimParams(command_ttl_ns=round(TTL_S * 1e9))
    sim = Simulator(open_floor(), {"r1": (0.0, 0.0, 0.0)}, params)
    r = sim.robots["r1"]
    sim.set_command("r1", V_MPS, 0.0)
    with caplog.at_level(logging.WARNING, logger="sim.simulator"):
        for _ in range(30):   # 3 s
            sim.advance()
    # it accelerates, drives out the 0.5 s and brakes: 0.5 s × v in all, then stands
    assert V_MPS * TTL_S * 0.9 < r.distance_m <= V_MPS * TTL_S + 1e-3
    assert r.v == 0.0 and r.cmd_expired
    assert r.commands_expired == 1 and len(caplog.records) == 1   # once, not every step
    # a new command (the same values, given now) drives again
    before = r.distance_m
    sim.set_command("r1", V_MPS, 0.0)
    sim.advance()
    assert r.distance_m > before and not r.cmd_expired
    # commands renewed every step never lapse
    for _ in range(30):
        sim.set_command("r1", V_MPS, 0.0)
        sim.advance()
    assert r.commands_expired == 1 and r.v == pytest.approx(V_MPS)
    # a stop that lapses is not counted: the robot was not moving on it
    sim.set_command("r1", 0.0, 0.0)
    for _ in range(30):
        sim.advance()
    assert r.commands_expired == 1


def test_without_a_time_to_live_a_command_holds_until_the_next() -> None:
    sim = Simulator(open_floor(), {"r1": (0.0, 0.0, 0.0)}, SimParams())
    sim.set_command("r1", V_MPS, 0.0)
    for _ in range(30):
        sim.advance()
    assert sim.robots["r1"].distance_m > 0.8 and sim.robots["r1"].commands_expired == 0


class Server:
    """Plays the server: answers every scan of r1 with 'drive straight on'."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.truth: SimGroundTruth | None = None
        bus.subscribe(keys.robot_scan("r1"), Scan, self._on_scan)
        bus.subscribe(keys.SIM_TRUTH, SimGroundTruth, self._on_truth)
        self.token = bus.declare_alive(keys.SERVER_ALIVE)

    def _on_scan(self, key: str, scan: Scan) -> None:
        self.bus.publish(keys.robot_cmd_vel("r1"), VelocityCommand(
            robot_id="r1", stamp_ns=scan.stamp_ns, v_mps=V_MPS, omega_rps=0.0, ttl_s=TTL_S))

    def _on_truth(self, key: str, msg: SimGroundTruth) -> None:
        self.truth = msg

    def distance_m(self) -> float:
        return self.truth.poses[0].distance_m if self.truth is not None else 0.0

    def sim_time_s(self) -> float:
        return self.truth.stamp_ns / 1e9 if self.truth is not None else 0.0


@pytest.fixture
def agent(endpoint: str, tmp_path: Path) -> Iterator[subprocess.Popen[bytes]]:
    """A real agent process for r1 (a thread cannot be frozen on its own)."""
    with open(tmp_path / "agent.log", "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "mrslam.cli", "agent", "--robot-id", "r1",
                                 "--connect", endpoint], cwd=ROOT, stdout=log, stderr=log)
        try:
            yield proc
        finally:
            os.kill(proc.pid, signal.SIGCONT)
            proc.terminate()
            proc.wait(timeout=30)


@pytest.mark.e2e
@pytest.mark.parametrize("lockstep", [False, True], ids=["real-time", "lockstep"])
def test_a_frozen_agent_leaves_its_robot_standing(router: Bus, endpoint: str, tmp_path: Path,
                                                  agent: subprocess.Popen[bytes],
                                                  lockstep: bool) -> None:
    server = Server(router)
    stop = threading.Event()
    result: dict[str, Any] = {}
    world = DEFAULT_SCENARIOS.parent / "large_house.world"
    overrides = {"world": str(world), "robots": {"r1": (-20.0, 0.0, 0.0)},  # down a corridor
                 "bus": {"connect": [endpoint]}, "lockstep": lockstep,
                 "real_time_factor": 1.0, "ack_timeout_s": 0.15, "command_ttl_s": TTL_S,
                 "camera": {"enabled": False}}

    def run() -> None:
        try:
            result["summary"] = process.run(None, overrides, stop)
        except Exception as e:  # surfaced below
            result["error"] = e

    thread = threading.Thread(target=run)
    thread.start()
    try:
        assert within(lambda: server.distance_m() > 0.5, 90.0), (
            result, (tmp_path / "agent.log").read_text()[-2000:])
        os.kill(agent.pid, signal.SIGSTOP)
        frozen_at_s, d0 = server.sim_time_s(), server.distance_m()
        # 2.5 s of simulated time: 0.75 m on the last command without a time-to-live
        assert within(lambda: server.sim_time_s() >= frozen_at_s + 2.5, 60.0)
        d1 = server.distance_m()
        os.kill(agent.pid, signal.SIGCONT)
        assert within(lambda: server.distance_m() > d1 + 0.2, 60.0)  # it drives on
    finally:
        stop.set()
        thread.join(timeout=30)
        server.token.undeclare()
    assert "error" not in result, result
    assert d1 - d0 < BOUND_M, (d0, d1)
    summary = result["summary"]
    assert summary["commands_expired"] >= 1 and summary["robots"]["r1"]["collisions"] == 0
