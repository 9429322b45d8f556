"""A real server process against a hostile network: floods of new robot ids, clocks that step,
stamps far off. Messages are made with our own encoders and sent over loopback Zenoh."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import zenoh

from bench.support.fleet import RoomRobot, ServerProcess, room_scan, rss_mb
from schemas import keys

#: starts other processes (the CLI, the server, the simulator, agents, scripts): the e2e tier
pytestmark = pytest.mark.e2e

HOUR_NS = 3600 * 1_000_000_000


@pytest.fixture
def server(tmp_path: Path):  # type: ignore[no-untyped-def]
    srv = ServerProcess(tmp_path, {"explore": {"total_area_m2": 48.0}})
    yield srv
    srv.stop()


def test_two_thousand_fake_ids_then_a_real_robot_is_served(server: ServerProcess,
                                                            tmp_path: Path) -> None:
    with server.client() as bus:
        rss0 = rss_mb(server.proc.pid)
        assert bus.wait_for_subscribers(keys.robot_scan("f0"), 10.0)
        for i in range(2000):   # blocking: on a loaded machine a dropping publisher lost some
            bus.publish(keys.robot_scan(f"f{i}"), room_scan(f"f{i}", 0, time.time_ns(), 0.0),
                        block=True)
        time.sleep(2.0)
        robot = RoomRobot(server.endpoint, "r1").start()
        try:
            t0 = time.monotonic()
            deadline = t0 + 20
            while robot.answered_since(t0) < 30 and time.monotonic() < deadline:
                time.sleep(0.1)
            assert robot.answered_since(t0) >= 30, "the real robot was not served"
            assert robot.longest_silence_s(t0 + 2.0, time.monotonic()) < 1.0
        finally:
            robot.close()
        rss1 = rss_mb(server.proc.pid)
    assert server.stop() == 0
    lines = server.log_lines()
    assert not any("Traceback" in ln for ln in lines)
    assert len(lines) <= 200, f"{len(lines)} log lines"
    summary = json.loads((tmp_path / "server" / "summary.json").read_text())
    assert summary["admission"]["on_probation"] == 2000   # held, cheaply, never processed
    assert list(summary["robots"]) == ["r1"]
    assert rss1 - rss0 < 100, f"server RSS grew {rss1 - rss0:.0f} MB"


def test_robots_whose_clocks_step_or_lie_keep_being_served(server: ServerProcess,
                                                           tmp_path: Path) -> None:
    """r1's clock steps back an hour; a scan stamped an hour ahead is sent under r2's name
    (a glitch or a stranger). Both robots go on being answered; the step is re-based and
    counted, the lone stamp refused and counted."""
    with server.client() as bus:
        r1 = RoomRobot(server.endpoint, "r1").start()
        r2 = RoomRobot(server.endpoint, "r2").start()
        try:
            time.sleep(4.0)
            t_step = time.monotonic()
            r1.clock_offset_ns = -HOUR_NS
            bus.publish(keys.robot_scan("r2"), room_scan("r2", 10**6, time.time_ns() + HOUR_NS,
                                                         0.0))
            time.sleep(6.0)
            t_end = time.monotonic()
            assert r1.longest_silence_s(t_step + 1.0, t_end) < 1.0
            assert r1.answered_since(t_step + 3.0) >= 20
            assert r2.longest_silence_s(t_step, t_end) < 1.0
        finally:
            r1.close()
            r2.close()
    assert server.stop() == 0
    summary = json.loads((tmp_path / "server" / "summary.json").read_text())
    reg = summary["registry"]
    assert reg["r1"]["clock_steps"] == 1 and reg["r1"]["clock_offset_s"] == pytest.approx(
        3600.0, abs=1.0)
    assert reg["r2"]["refused_clock-skew"] == 1 and "clock_steps" not in reg["r2"]
    assert summary["errors"] == 0
    lines = server.log_lines()
    assert sum("clock stepped" in ln for ln in lines) == 1


@pytest.mark.parametrize("cap", [None, 65536])
def test_the_server_applies_its_configured_message_size_cap(tmp_path: Path, cap: int | None
                                                            ) -> None:
    """80 kB of garbage on r1's scan key: under the default cap it reaches the decoder (and
    is refused there); under a 64 kB cap it is dropped by size before anything reads it."""
    srv = ServerProcess(tmp_path, {"bus": {"max_message_size": cap} if cap else {},
                                   "explore": {"total_area_m2": 48.0}})
    try:
        with srv.client() as bus:
            robot = RoomRobot(srv.endpoint, "r1").start()   # 360 beams: under 1 kB a scan
            # a client that has not yet learnt of the server's subscription sends into nothing
            assert bus.wait_for_subscribers(keys.robot_scan("r1"), 10.0)
            for _ in range(5):   # valid scans are never this big: 8,192 beams at most
                bus.session.put(keys.robot_scan("r1"), b"\x00" * 80_000,
                                congestion_control=zenoh.CongestionControl.BLOCK)
            t0 = time.monotonic()
            time.sleep(3.0)
            assert robot.answered_since(t0) >= 20
            robot.close()
    finally:
        assert srv.stop() == 0
    stats = json.loads((tmp_path / "server" / "summary.json").read_text())["bus"]
    if cap is None:
        assert stats["rejected"] == {"Scan": 5}
        assert "max_message_size" not in stats["last_error"]
    else:   # Zenoh's own limit drops some on the link; the bus drops the rest by size
        assert not stats["rejected"] or "max_message_size" in stats["last_error"]


def test_commands_published_by_anyone_but_the_server_are_counted(server: ServerProcess,
                                                                  tmp_path: Path) -> None:
    """Without access rules (a loopback server, --insecure) nothing stops a client from
    publishing on a robot's cmd_vel; the agent ignores such commands, and the server, which
    sees them, counts and logs them."""
    from schemas import VelocityCommand

    with server.client() as bus:
        robot = RoomRobot(server.endpoint, "r1").start()
        try:
            time.sleep(2.0)
            for _ in range(5):
                bus.publish(keys.robot_cmd_vel("r1"), VelocityCommand(
                    robot_id="r1", stamp_ns=time.time_ns(), v_mps=0.5, omega_rps=0.0),
                    block=True)
                time.sleep(0.05)
            time.sleep(1.0)
        finally:
            robot.close()
    assert server.stop() == 0
    summary = json.loads((tmp_path / "server" / "summary.json").read_text())
    assert summary["foreign_commands"] == {"r1": 5}    # the server's own are not counted
    assert sum("not this server" in ln for ln in server.log_lines()) == 5


def test_a_flood_of_valid_newcomers_does_not_starve_a_robot_with_a_token(
        server: ServerProcess, tmp_path: Path) -> None:
    """2,000 ids nobody runs send three valid, current scans each (the default config: any
    robot may join). r1, which holds its liveliness token, keeps being answered within a
    second; the newcomers join at a bounded rate; the server's memory stays bounded and it
    stops at once."""
    with server.client() as bus:
        robot = RoomRobot(server.endpoint, "r1").start()
        try:
            time.sleep(3.0)
            rss0 = rss_mb(server.proc.pid)
            assert bus.wait_for_subscribers(keys.robot_scan("f0"), 10.0)
            t0 = time.monotonic()
            for k in range(3):
                for i in range(2000):
                    bus.publish(keys.robot_scan(f"f{i}"),
                                room_scan(f"f{i}", k, time.time_ns(), 0.1 * k), block=True)
            time.sleep(15.0)
            share = robot.answered_within(t0, time.monotonic() - 1.0, 1.0)
            rss1 = rss_mb(server.proc.pid)
        finally:
            robot.close()
    t_stop = time.monotonic()
    assert server.stop() == 0
    assert time.monotonic() - t_stop <= 5.0
    assert share >= 0.95, f"r1 answered within 1 s for {share:.0%} of its scans"
    assert rss1 - rss0 <= 150, f"server RSS grew {rss1 - rss0:.0f} MB"
    admission = json.loads((tmp_path / "server" / "summary.json").read_text())["admission"]
    assert admission["joined"] <= 10 + 2 * 30 + 1      # the burst, then 2 a second
