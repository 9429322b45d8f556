"""A real ``mrslam server --console`` with stand-in robots, and plain HTTP to its console, for
the console's tests."""

from __future__ import annotations

import http.client
import json
import socket
from pathlib import Path
from typing import Any

from bench.support.fleet import RoomRobot, ServerProcess
from server.console.service import TOKEN_ENV

TOKEN = "console-test-token-0123456789"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_server(folder: Path, port: int, config: dict[str, Any] | None = None
                 ) -> ServerProcess:
    return ServerProcess(folder, {"robots": ["r1", "r2"], "outputs_period_s": 0.5,
                                  **(config or {})},
                         args=("--console", str(port)), env={TOKEN_ENV: TOKEN})


def request(port: int, method: str, path: str, token: str | None = TOKEN,
            body: Any = None, raw: bytes | None = None, in_query: bool = False,
            timeout_s: float = 30.0) -> tuple[int, bytes]:
    """One request to the console; the token as a bearer header (or in the query)."""
    headers = {}
    if token is not None and in_query:
        path += ("&" if "?" in path else "?") + f"token={token}"
    elif token is not None:
        headers["Authorization"] = f"Bearer {token}"
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    if data is not None:
        headers["Content-Type"] = "application/json"
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout_s)
    try:
        conn.request(method, path, body=data, headers=headers)
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


def state(port: int) -> dict[str, Any]:
    status, body = request(port, "GET", "/state")
    assert status == 200, (status, body)
    return dict(json.loads(body))


def try_state(port: int) -> dict[str, Any] | None:
    try:
        return state(port)
    except (OSError, AssertionError):
        return None


def command(port: int, **order: Any) -> tuple[int, dict[str, Any]]:
    status, body = request(port, "POST", "/command", body=order)
    return status, dict(json.loads(body))


def robots_moving_after(robots: list[RoomRobot], t_mono: float) -> list[bool]:
    """Per robot: whether any command it got after ``t_mono`` was not a stop."""
    return [any(t >= t_mono and (c.v_mps != 0 or c.omega_rps != 0) for t, c in r.commands)
            for r in robots]


def commands_after(robot: RoomRobot, t_mono: float) -> list[tuple[float, float]]:
    return [(c.v_mps, c.omega_rps) for t, c in list(robot.commands) if t >= t_mono]
