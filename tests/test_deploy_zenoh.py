"""Secured deployment on loopback: mutual TLS and per-robot access control in the router."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from schemas import MapUpdate, Scan, VelocityCommand, keys
from schemas.bus import Bus, BusError, free_local_endpoint
from tests.conftest import ROOT
from tests.examples import all_examples, scan

DEPLOY = ROOT / "deploy" / "zenoh"
#: runs the deploy scripts and starts processes on them: the e2e tier
pytestmark = [pytest.mark.e2e,
              pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")]


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    subprocess.run(["bash", str(DEPLOY / "make-certs.sh"), str(out), "127.0.0.1", "r1", "r2",
                    "dashboard", "worker1"], check=True, capture_output=True)
    return out


def write_config(tmp: Path, name: str, *args: str) -> str:
    out = subprocess.run([sys.executable, str(DEPLOY / "config.py"), *args], check=True,
                         capture_output=True, text=True).stdout
    json.loads(out)  # the generated file is valid JSON (hence json5)
    path = tmp / f"{name}.json5"
    path.write_text(out)
    return str(path)


@pytest.fixture
def secured(certs: Path, tmp_path: Path) -> Iterator[tuple[Bus, str, Path]]:
    endpoint = free_local_endpoint().replace("tcp/", "tls/")
    conf = write_config(tmp_path, "server", "server", "--certs", str(certs), "--listen",
                        endpoint, "--observer", "dashboard", "--worker", "worker1", "r1", "r2")
    with Bus.open("router", config_file=conf) as server:
        yield server, endpoint, tmp_path


def client(certs: Path, tmp: Path, endpoint: str, name: str) -> Bus:
    role = ["agent", "--robot", name] if name.startswith("r") else ["client", "--name", name]
    conf = write_config(tmp, name, role[0], "--certs", str(certs), "--connect", endpoint,
                        *role[1:])
    return Bus.open("client", config_file=conf, connect_timeout_ms=3000)


def wait_for(cond: object, timeout_s: float = 3.0) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if cond():  # type: ignore[operator]
            return True
        time.sleep(0.02)
    return bool(cond())  # type: ignore[operator]


def stream_arrives(bus: Bus, robot: str, first_seq: int, seqs_seen: Callable[[], set[int]],
                   n: int = 30) -> bool:
    """Publish ``n`` scans at 20 Hz as an agent does: does every one of them arrive?

    (Before the robots were allowed to hear of the server's subscriptions, a client's declared
    publisher delivered its first put at most and dropped the rest.)
    """
    if not bus.wait_for_subscribers(keys.robot_scan(robot), timeout_s=15.0):
        return False  # the robot never heard of the server's subscription
    want = set(range(first_seq, first_seq + n))
    for q in sorted(want):
        bus.publish(keys.robot_scan(robot), scan(robot, seq=q), block=True)
        time.sleep(0.05)
    wait_for(lambda: want <= seqs_seen(), 3.0)
    return want <= seqs_seen()


def test_client_without_a_valid_certificate_cannot_connect(
        secured: tuple[Bus, str, Path], tmp_path: Path) -> None:
    _, endpoint, _ = secured
    # plain TCP to a TLS listener
    with pytest.raises(BusError):
        Bus.open("client", connect=[endpoint.replace("tls/", "tcp/")], connect_timeout_ms=800)
    # TLS with a certificate from another CA
    rogue = tmp_path / "rogue"
    subprocess.run(["bash", str(DEPLOY / "make-certs.sh"), str(rogue), "127.0.0.1", "r1"],
                   check=True, capture_output=True)
    conf = write_config(tmp_path, "rogue", "agent", "--certs", str(rogue), "--connect",
                        endpoint, "--robot", "r1")
    with pytest.raises(BusError):
        Bus.open("client", config_file=conf, connect_timeout_ms=800)


def test_robot_can_publish_only_under_its_own_keys(
        secured: tuple[Bus, str, Path], certs: Path) -> None:
    server, endpoint, tmp = secured
    got: list[tuple[str, str, int]] = []
    lock = threading.Lock()

    def on_scan(key: str, msg: Scan) -> None:
        with lock:
            got.append((key, msg.robot_id, msg.seq))

    server.subscribe(keys.ALL_SCANS, Scan, on_scan)
    maps: list[MapUpdate] = []
    r1 = client(certs, tmp, endpoint, "r1")
    r2 = client(certs, tmp, endpoint, "r2")
    rogue = client(certs, tmp, endpoint, "r2")  # a second session with r2's credentials
    dash = client(certs, tmp, endpoint, "dashboard")
    spoof_seq = 1_000_000  # refused scans carry sequence numbers from here on
    try:
        cmds: list[VelocityCommand] = []
        r1.subscribe(keys.robot_cmd_vel("r1"), VelocityCommand, lambda k, m: cmds.append(m))
        dash.subscribe(keys.SERVER_MAP, MapUpdate, lambda k, m: maps.append(m))
        spoofed: list[MapUpdate] = []
        server.subscribe(keys.SERVER_MAP, MapUpdate, lambda k, m: spoofed.append(m))

        def arrived() -> bool:
            with lock:
                scans = {(k, r) for k, r, _ in got}
            return scans == {("mrslam/robot/r1/scan", "r1"),
                             ("mrslam/robot/r2/scan", "r2")} and bool(cmds)

        # 1. allowed traffic: subscriptions take a moment to reach the router (longer on a busy
        # machine), so send again until it arrives
        deadline = time.monotonic() + 15.0
        seq = 0
        while not arrived() and time.monotonic() < deadline:
            seq += 2
            r2.publish(keys.robot_scan("r2"), scan("r2", seq=seq), block=True)
            r1.publish(keys.robot_scan("r1"), scan("r1", seq=seq + 1), block=True)
            server.publish(keys.robot_cmd_vel("r1"), VelocityCommand(
                robot_id="r1", v_mps=0.1, omega_rps=0.0), block=True)
            wait_for(arrived, 0.5)
        assert arrived(), (got, cmds)
        # 2. refused: r2's credentials writing r1's scans and the server's map, repeatedly
        for i in range(10):
            rogue.publish(keys.robot_scan("r1"), scan("r1", seq=spoof_seq + i), block=True)
            rogue.publish(keys.SERVER_MAP, all_examples()["MapUpdate"], block=True)
            time.sleep(0.05)
        time.sleep(1.0)  # would a refused message still arrive?
        with lock:
            assert not [g for g in got if g[2] >= spoof_seq]
            assert {(k, r) for k, r, _ in got} == {("mrslam/robot/r1/scan", "r1"),
                                                   ("mrslam/robot/r2/scan", "r2")}
        assert {c.robot_id for c in cmds} == {"r1"}
        assert spoofed == [] and maps == []
        # 3. a robot's stream arrives whole, also after refused attempts under its key

        def seqs(robot: str) -> Callable[[], set[int]]:
            def seen() -> set[int]:
                with lock:
                    return {q for _, r, q in got if r == robot}
            return seen

        assert stream_arrives(r1, "r1", 5000, seqs("r1"))
        assert stream_arrives(r2, "r2", 5000, seqs("r2"))
        server.publish(keys.SERVER_MAP, all_examples()["MapUpdate"], block=True)
        assert wait_for(lambda: len(maps) == 1)  # observers read what the server publishes
    finally:
        for b in (r1, r2, rogue, dash):
            b.close()


def test_a_server_worker_may_serve_robots_and_a_robot_may_not_pose_as_one(
        secured: tuple[Bus, str, Path], certs: Path) -> None:
    """Another worker of the server (``server.runtime.cluster``) claims robots and answers for teams
    through the router; a robot's certificate cannot claim anything there, nor ask for a team,
    but it sees which worker serves it (its agent obeys that one)."""
    server, endpoint, tmp = secured
    owners: list[tuple[str, bool]] = []
    server.watch_alive(keys.ALL_CLUSTER_OWNERS, lambda k, alive: owners.append((k, alive)))
    server.serve_queries(keys.cluster_give(0), lambda q: (q.reply(keys.cluster_give(0), b"ok"),
                                                          q.drop()))
    robot = client(certs, tmp, endpoint, "r1")
    worker = client(certs, tmp, endpoint, "worker1")
    try:
        seen: list[tuple[str, bool]] = []
        robot.watch_alive(keys.cluster_owners("r1"), lambda k, alive: seen.append((k, alive)))
        robot.watch_alive(keys.ALL_CLUSTER_WORKER_SESSIONS,
                          lambda k, alive: seen.append((k, alive)))
        robot.declare_token(keys.cluster_owner("r2", 1))
        worker.declare_alive(keys.cluster_worker(1))
        worker.declare_token(keys.cluster_owner("r1", 1))
        assert wait_for(lambda: (keys.cluster_owner("r1", 1), True) in owners, 5.0)
        assert wait_for(lambda: (keys.cluster_owner("r1", 1), True) in seen, 5.0)
        assert wait_for(lambda: any(keys.cluster_worker_session_of(k) == (1, worker.zid)
                                    for k, _ in seen), 5.0)
        answers: list[list[bytes]] = []
        worker.ask(keys.cluster_give(0), b"{}", lambda r, e: answers.append(r), 3.0)
        assert wait_for(lambda: answers == [[b"ok"]], 5.0)
        refused: list[list[bytes]] = []
        robot.ask(keys.cluster_give(0), b"{}", lambda r, e: refused.append(r), 2.0)
        time.sleep(0.5)
        assert (keys.cluster_owner("r2", 1), True) not in owners
        assert wait_for(lambda: refused == [[]], 5.0)      # no team for a robot's certificate
    finally:
        robot.close()
        worker.close()
