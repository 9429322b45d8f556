"""Foxglove live: the SDK's WebSocket server is reachable and advertises the run's channels.

The client is a plain socket speaking the WebSocket handshake and framing (RFC 6455) and
Foxglove's protocol on top: a ``serverInfo`` then ``advertise`` messages naming each channel's
topic and schema."""

from __future__ import annotations

import base64
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import msgspec
import pytest

from recording.live import FoxgloveLive, FoxgloveLiveError
from schemas import RobotEstimate, RobotStates, encode, keys
from schemas.bus import Bus
from tests.examples import STAMP, scan

ROOT = Path(__file__).resolve().parent.parent
PROTOCOLS = "foxglove.sdk.v1, foxglove.websocket.v1"


class WsClient:
    """Just enough of a WebSocket client to read a server's text messages."""

    def __init__(self, port: int, timeout_s: float = 10.0) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {PROTOCOLS}"
                           "\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            assert chunk, f"connection closed during the handshake: {head!r}"
            head += chunk
        self.status = head.split(b"\r\n", 1)[0].decode()
        self.headers = head.decode(errors="replace").lower()

    def _exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            assert chunk, "connection closed"
            buf += chunk
        return buf

    def frame(self) -> tuple[int, bytes]:
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        return b0 & 0x0F, self._exact(n)   # server frames are not masked

    def json_messages(self, until: Any, limit: int = 200) -> list[dict[str, Any]]:
        """Text messages until ``until(messages)`` holds (binary ones skipped)."""
        out: list[dict[str, Any]] = []
        for _ in range(limit):
            op, payload = self.frame()
            if op == 1:
                out.append(json.loads(payload))
                if until(out):
                    return out
        raise AssertionError(f"not seen in {limit} frames: {[m.get('op') for m in out]}")

    def close(self) -> None:
        self.sock.close()


def advertised(msgs: list[dict[str, Any]]) -> dict[str, str]:
    return {ch["topic"]: ch["schemaName"] for m in msgs if m.get("op") == "advertise"
            for ch in m["channels"]}


def test_live_server_advertises_the_channels_of_what_it_was_fed() -> None:
    with FoxgloveLive(0) as live:
        live.add(keys.robot_scan("r1"), encode(scan("r1")))
        client = WsClient(live.port)
        try:
            assert " 101 " in client.status and "sec-websocket-protocol: foxglove" in \
                client.headers
            msgs = client.json_messages(lambda ms: "foxglove/robot/r1/scan" in advertised(ms))
            assert msgs[0]["op"] == "serverInfo" and msgs[0]["name"] == "mrslam"
            got = advertised(msgs)
            assert got["foxglove/robot/r1/scan"] == "foxglove.LaserScan"
            assert got["foxglove/tf"] == "foxglove.FrameTransforms"
            # a channel that appears while the client is connected is advertised then
            live.add(keys.SERVER_ROBOTS, encode(RobotStates(stamp_ns=STAMP, robots=[
                RobotEstimate(robot_id="r1", team_id="t1", pose=(1.0, 2.0, 0.3))])))
            later = client.json_messages(lambda ms: "foxglove/robot/r1/pose" in advertised(ms))
            assert advertised(later)["foxglove/robot/r1/pose"] == "foxglove.PoseInFrame"
        finally:
            client.close()
        assert live.published >= 5 and live.errors == 0
        live.add(keys.robot_scan("r1"), b"\x00not msgpack")   # counted, not raised
        assert live.errors == 1


def test_a_port_in_use_is_a_typed_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(FoxgloveLiveError, match=str(s.getsockname()[1])):
            FoxgloveLive(s.getsockname()[1])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.e2e
def test_recorder_serves_the_bus_live(tmp_path: Path, endpoint: str, router: Bus) -> None:
    """``mrslam record --foxglove PORT``: what robots publish is advertised to a client."""
    port = _free_port()
    out = tmp_path / "run.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "mrslam", "record", "--out", str(out),
                             "--connect", endpoint, "--foxglove", str(port)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while not out.exists() and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""
            time.sleep(0.1)
        with Bus.open("client", connect=[endpoint]) as pub:
            assert pub.wait_for_subscribers(keys.robot_scan("r2"), timeout_s=30)
            for k in range(5):
                pub.publish(keys.robot_scan("r2"), msgspec.structs.replace(
                    scan("r2", seq=k), stamp_ns=10**9 + k * 10**8), block=True)
            time.sleep(0.5)
            client = WsClient(port)
            try:
                msgs = client.json_messages(
                    lambda ms: "foxglove/robot/r2/scan" in advertised(ms))
            finally:
                client.close()
        assert advertised(msgs)["foxglove/robot/r2/scan"] == "foxglove.LaserScan"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
