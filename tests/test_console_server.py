"""The console of a real ``mrslam server`` with robots on the wire: nothing without the token,
orders that reach the robots' commands, bad requests answered and counted, a page that stops
reading dropped without holding anything up, and a stop-all that still holds after the server
is killed with SIGKILL and started again."""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.support.fleet import RoomRobot, ServerProcess
from tests.console_support import (
    TOKEN,
    command,
    commands_after,
    free_port,
    request,
    robots_moving_after,
    start_server,
    state,
    try_state,
)
from tests.waiting import within

pytestmark = pytest.mark.e2e


Fleet = tuple[int, ServerProcess, list[RoomRobot]]


@pytest.fixture
def fleet(tmp_path: Path) -> Iterator[Fleet]:
    """A server with its console on a free port, and two robots it is serving."""
    port = free_port()
    srv = start_server(tmp_path, port)
    srv.client().close()
    robots = [RoomRobot(srv.endpoint, rid).start() for rid in ("r1", "r2")]
    try:
        assert within(lambda: len((try_state(port) or {}).get("robots", [])) == 2, 90)
        yield port, srv, robots
    finally:
        for r in robots:
            r.close()
        srv.stop()


def test_without_the_right_token_there_is_no_page_no_data_and_no_control(fleet: Fleet) -> None:
    port, _srv, robots = fleet
    for token in (None, "", "wrong", TOKEN[:-1], TOKEN + "x", TOKEN.upper()):
        for method, path in (("GET", "/"), ("GET", "/state"), ("GET", "/stream"),
                             ("GET", "/nothing"), ("POST", "/command")):
            for in_query in (False, True):
                status, body = request(port, method, path, token=token, in_query=in_query,
                                       body={"action": "stop"} if method == "POST" else None)
                assert (status, body) == (401, b""), (token, method, path)
    # the stops sent without the token did nothing
    s = state(port)
    assert s["health"]["orders"]["stop_all"] is False
    assert not [e for e in s["events"] if e["kind"] == "operator"]
    assert s["health"]["console"]["unauthorised"] >= 60
    t = time.monotonic()
    assert within(lambda: all(robots_moving_after(robots, t)), 60)
    # with it: the page, the state and the stream
    status, page = request(port, "GET", "/")
    assert status == 200 and b'data-testid="map-canvas"' in page
    status, page = request(port, "GET", "/", in_query=True)
    assert status == 200 and b"<script>" in page


def test_stop_all_holds_every_robot_until_resumed(fleet: Fleet) -> None:
    port, _srv, robots = fleet
    t0 = time.monotonic()
    assert within(lambda: all(robots_moving_after(robots, t0)), 60)
    status, answer = command(port, action="stop")
    assert status == 200 and answer["ok"] is True, answer
    t_stop = time.monotonic()
    # every command from the answer on is a stop, for as long as it is held
    assert within(lambda: all(len(commands_after(r, t_stop)) >= 30 for r in robots), 60)
    for r in robots:
        assert set(commands_after(r, t_stop)) == {(0.0, 0.0)}, r.robot_id
    s = state(port)
    assert s["health"]["orders"]["stop_all"] is True
    assert {r["mode"] for r in s["robots"]} == {"idle"}
    assert any("stop every robot" in e["message"] for e in s["events"])
    status, answer = command(port, action="resume")
    assert status == 200 and answer["ok"] is True
    t_resume = time.monotonic()
    assert within(lambda: all(robots_moving_after(robots, t_resume)), 60)
    # one robot alone
    status, _ = command(port, action="stop", robot_id="r2")
    t_one = time.monotonic()
    assert status == 200
    assert within(lambda: len(commands_after(robots[1], t_one)) >= 20, 60)
    assert set(commands_after(robots[1], t_one)) == {(0.0, 0.0)}
    assert within(lambda: robots_moving_after(robots, t_one)[0], 60)


def test_bad_requests_get_a_reason_and_are_counted(fleet: Fleet) -> None:
    port, srv, robots = fleet
    cases = [
        (b"{not json", 400, "not JSON"),
        (b"\xff\xfe", 400, "not JSON"),
        (b"[1, 2]", 400, "JSON object"),
        (json.dumps({"action": "fly"}).encode(), 400, "action"),
        (json.dumps({"action": "goto", "robot_id": "r1", "point": [1e999, 0]})
         .encode().replace(b"Infinity", b"1e999"), 400, "point"),
        (json.dumps({"action": "goto", "robot_id": "r1", "point": "here"}).encode(), 400,
         "point"),
        (json.dumps({"action": "stop", "robot_id": "r9"}).encode(), 404, "no robot r9"),
        (json.dumps({"action": "goto", "robot_id": "r1", "point": [900, 900]}).encode(), 409,
         "no way for r1"),
    ]
    for raw, status, reason in cases:
        got, body = request(port, "POST", "/command", raw=raw)
        answer = json.loads(body)
        assert got == status and reason in answer["error"] and answer["ok"] is False, (raw, body)
    got, _ = request(port, "POST", "/command", raw=b"x" * 10_000)
    assert got == 400
    got, _ = request(port, "POST", "/elsewhere", body={"action": "stop"})
    assert got == 404
    got, _ = request(port, "DELETE", "/command")
    assert got == 405
    counters = state(port)["health"]["console"]
    assert counters["bad_commands"] >= 6 and counters["commands_refused"] >= 2
    assert counters["bad_requests"] >= 3
    # the server took no harm: it still serves the robots and the console
    t = time.monotonic()
    assert within(lambda: all(r.answered_since(t) > 10 for r in robots), 60)
    assert srv.proc.poll() is None


def test_a_page_that_stops_reading_holds_nothing_up(fleet: Fleet) -> None:
    port, _srv, robots = fleet
    hung = []
    for _ in range(3):
        s = socket.create_connection(("127.0.0.1", port))
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.sendall(f"GET /stream?token={TOKEN} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        hung.append(s)                  # ... and never read
    try:
        assert within(lambda: state(port)["health"]["console"]["pages"] >= 3, 30)
        t = time.monotonic()
        status, _answer = command(port, action="stop", robot_id="r1")
        assert status == 200
        assert within(lambda: len(commands_after(robots[0], t)) >= 20, 60)
        assert all(r.answered_since(t) > 10 for r in robots)
    finally:
        for s in hung:
            s.close()
    assert within(lambda: state(port)["health"]["console"]["pages"] == 0, 60)
    # a flood of idle connections: those past the limit are closed at once, and once they
    # go the console serves again
    flood = [socket.create_connection(("127.0.0.1", port)) for _ in range(80)]
    try:
        refused = 0
        for s in flood:
            s.settimeout(0.5)
            with contextlib.suppress(TimeoutError):   # held open, waiting for a request
                refused += s.recv(1) == b""           # closed by the server, nothing sent
        assert refused >= 10
    finally:
        for s in flood:
            s.close()
    assert within(lambda: try_state(port) is not None, 60)
    assert state(port)["health"]["console"]["connections_refused"] >= 10
    t = time.monotonic()
    assert within(lambda: all(r.answered_since(t) > 10 for r in robots), 60)


def test_a_stop_all_still_holds_after_a_sigkill_and_a_restart(tmp_path: Path) -> None:
    port = free_port()
    srv = start_server(tmp_path, port)
    srv.client().close()
    robots = [RoomRobot(srv.endpoint, rid).start() for rid in ("r1", "r2")]
    servers = [srv]
    try:
        assert within(lambda: len((try_state(port) or {}).get("robots", [])) == 2, 90)
        status, _ = command(port, action="stop")
        assert status == 200
        time.sleep(1.5)       # past the journal's one-second flush
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(timeout=10)
        srv.stop()
        srv2 = start_server(tmp_path, port, {"bus": {"listen": [srv.endpoint]}})
        srv2.endpoint = srv.endpoint
        servers.append(srv2)
        t = time.monotonic()
        assert within(lambda: (try_state(port) or {}).get("health", {}).get("orders", {})
                      .get("stop_all") is True, 90)
        assert within(lambda: all(len(commands_after(r, t)) >= 20 for r in robots), 90)
        for r in robots:
            assert set(commands_after(r, t)) == {(0.0, 0.0)}, r.robot_id
        status, _ = command(port, action="resume")
        assert status == 200
        t = time.monotonic()
        assert within(lambda: all(robots_moving_after(robots, t)), 60)
    finally:
        for r in robots:
            r.close()
        for s in servers:
            s.stop()
