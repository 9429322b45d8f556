"""Helpers for the network-security tests and bench sections: this machine's address as others
see it, a server process with a given ``bus`` config, and whether a client reaches it."""

from __future__ import annotations

import contextlib
import ipaddress
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from schemas import keys
from schemas.bus import Bus, BusError

ROOT = Path(__file__).resolve().parents[2]


def primary_ip() -> str | None:
    """The IPv4 address other machines reach this one on (None when it has only loopback)."""
    candidates: list[str] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s, \
            contextlib.suppress(OSError):
        s.connect(("192.0.2.1", 9))   # no packet is sent: this only picks a route
        candidates.append(s.getsockname()[0])
    with contextlib.suppress(OSError):
        candidates += [str(a[4][0]) for a in socket.getaddrinfo(socket.gethostname(), None,
                                                                 socket.AF_INET)]
    for ip in candidates:
        if not ipaddress.ip_address(ip).is_loopback:
            return ip
    return None


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


def start_server(folder: Path, bus: dict[str, Any] | None, *args: str,
                 extra: dict[str, Any] | None = None) -> subprocess.Popen[bytes]:
    """``mrslam server -c folder/server.yaml ARGS`` with ``bus`` (None: the default bus);
    stdout and stderr go to ``folder/server.log``."""
    cfg: dict[str, Any] = {**(extra or {})}
    if bus is not None:
        cfg["bus"] = bus
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "server.yaml").write_text(yaml.safe_dump(cfg))
    with open(folder / "server.log", "wb") as log:
        return subprocess.Popen(
            [sys.executable, "-m", "mrslam", "server", "-c", str(folder / "server.yaml"), *args],
            cwd=ROOT, stdout=log, stderr=log, env={**os.environ, "PYTHONPATH": str(ROOT)})


def connect(endpoint: str, timeout_ms: int = 1500) -> Bus | None:
    """A client session on ``endpoint``, or None when it cannot connect."""
    try:
        return Bus.open("client", connect=[endpoint], connect_timeout_ms=timeout_ms)
    except BusError:
        return None


def wait_up(endpoint: str, proc: subprocess.Popen[bytes], timeout_s: float = 60.0) -> Bus:
    """A client on ``endpoint`` once the server process there holds its liveliness token."""
    deadline = time.monotonic() + timeout_s
    while True:
        bus = connect(endpoint, 500)
        if bus is not None:
            break
        if time.monotonic() > deadline or proc.poll() is not None:
            raise BusError(f"the server on {endpoint} did not come up")
        time.sleep(0.2)
    alive: list[bool] = []
    bus.watch_alive(keys.SERVER_ALIVE, lambda _k, up: alive.append(up))
    while not alive and time.monotonic() < deadline:
        time.sleep(0.05)
    if not alive:
        bus.close()
        raise BusError("the server's liveliness token never appeared")
    return bus


def stop(proc: subprocess.Popen[bytes]) -> int:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return int(proc.returncode)
