"""With the deploy configs' TLS and access rules, only the server reaches a robot's ``cmd_vel``:
another robot's or a dashboard's commands are stopped by the router before the agent sees them,
and the agent, through the same rules, learns which session is the server (issue 20, item 4)."""

from __future__ import annotations

import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from robot_agent.backend import Backend
from robot_agent.config import AgentConfig
from robot_agent.runtime import Agent
from schemas import VelocityCommand, keys
from schemas.bus import Bus, free_local_endpoint
from tests.test_agent_command_gate import NoLidar, StillBase
from tests.test_deploy_zenoh import DEPLOY, client, write_config
from tests.waiting import within

#: runs the deploy scripts and starts processes on them: the e2e tier
pytestmark = [pytest.mark.e2e,
              pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")]


def test_only_the_server_commands_a_robot(tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    subprocess.run(["bash", str(DEPLOY / "make-certs.sh"), str(certs), "127.0.0.1", "r1", "r2",
                    "dashboard"], check=True, capture_output=True)
    endpoint = free_local_endpoint().replace("tcp/", "tls/")
    conf = write_config(tmp_path, "server", "server", "--certs", str(certs), "--listen",
                        endpoint, "--observer", "dashboard", "r1", "r2")
    key = keys.robot_cmd_vel("r1")
    base = StillBase()
    stop = threading.Event()
    with Bus.open("router", config_file=conf) as server:
        server.declare_alive(keys.SERVER_ALIVE)
        r1, r2, dash = (client(certs, tmp_path, endpoint, n) for n in ("r1", "r2", "dashboard"))
        agent = Agent(AgentConfig.model_validate({"robot_id": "r1",
                                                  "detector": {"enabled": False}}),
                      r1, Backend(lidar=NoLidar(), base=base, camera=None, now_ns=time.time_ns))
        agent.start()
        thread = threading.Thread(target=agent.run, args=(stop,))
        thread.start()
        try:
            # the agent learns the server's session through the rules (its token is readable)
            assert within(lambda: agent.gate.server == server.zid, 15.0)
            deadline = time.monotonic() + 15.0
            while agent.counters["commands_received"] == 0 and time.monotonic() < deadline:
                for stranger in (r2, dash):
                    stranger.publish(key, VelocityCommand(robot_id="r1", stamp_ns=time.time_ns(),
                                                          v_mps=0.5, omega_rps=2.0), block=True)
                server.publish(key, VelocityCommand(robot_id="r1", stamp_ns=time.time_ns(),
                                                    v_mps=0.2, omega_rps=0.0), block=True)
                time.sleep(0.2)
            assert agent.counters["commands_received"] >= 1
            for _ in range(10):   # more attempts, once the routes are surely in place
                for stranger in (r2, dash):
                    stranger.publish(key, VelocityCommand(robot_id="r1", stamp_ns=time.time_ns(),
                                                          v_mps=0.5, omega_rps=2.0), block=True)
                time.sleep(0.05)
            time.sleep(1.0)   # would a refused command still arrive?
            # refused by the router: the agent never saw them, so had nothing to ignore
            assert agent.counters["commands_ignored"] == 0
            assert all(v != 0.5 for v, _ in base.velocities) and (0.2, 0.0) in base.velocities
        finally:
            stop.set()
            thread.join(timeout=10)
            for b in (r1, r2, dash):
                b.close()


def test_a_robot_certificate_cannot_command_its_own_robot(tmp_path: Path) -> None:
    """A second session with r1's certificate (a stolen robot key, a confused script) may
    publish r1's scans but never r1's commands: the router refuses them before anyone, the
    server included, sees them. r1 still hears the server."""
    certs = tmp_path / "certs"
    subprocess.run(["bash", str(DEPLOY / "make-certs.sh"), str(certs), "127.0.0.1", "r1"],
                   check=True, capture_output=True)
    endpoint = free_local_endpoint().replace("tcp/", "tls/")
    conf = write_config(tmp_path, "server", "server", "--certs", str(certs), "--listen",
                        endpoint, "r1")
    key = keys.robot_cmd_vel("r1")
    with Bus.open("router", config_file=conf) as server:
        seen_by_server: list[VelocityCommand] = []
        server.subscribe(key, VelocityCommand, lambda _k, m: seen_by_server.append(m))
        r1, forger = (client(certs, tmp_path, endpoint, "r1") for _ in range(2))
        got: list[VelocityCommand] = []
        try:
            r1.subscribe(key, VelocityCommand, lambda _k, m: got.append(m))
            assert within(lambda: server.wait_for_subscribers(key, 0.2), 15.0)
            assert within(lambda: (server.publish(key, VelocityCommand(
                robot_id="r1", v_mps=0.2, omega_rps=0.0), block=True), bool(got))[1], 15.0)
            for _ in range(10):
                forger.publish(key, VelocityCommand(robot_id="r1", v_mps=0.5, omega_rps=2.0),
                               block=True)
                time.sleep(0.05)
            time.sleep(1.0)   # would a refused command still arrive?
            assert all(c.v_mps == 0.2 for c in got)
            assert all(c.v_mps == 0.2 for c in seen_by_server)
        finally:
            r1.close()
            forger.close()
