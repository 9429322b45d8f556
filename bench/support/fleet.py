"""A real server process and stand-in robots on loopback, for hostile tests and benches.

``ServerProcess`` runs ``mrslam server`` as its own process (its log captured to a file), and
``RoomRobot`` is a client session that behaves like an agent on the wire: it holds a liveliness
token, streams scans of a room at 10 Hz stamped by its own clock (which the caller can step),
and counts the velocity commands the server sends back for them.
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from schemas import Scan, VelocityCommand, keys, quantise_ranges_mm
from schemas.bus import Bus, BusError, free_local_endpoint

ROOT = Path(__file__).resolve().parents[2]


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


class ServerProcess:
    """``mrslam server`` on a free loopback port; ``config`` is merged into the defaults."""

    def __init__(self, folder: Path, config: dict[str, Any] | None = None,
                 args: tuple[str, ...] = (), env: dict[str, str] | None = None,
                 prefix: tuple[str, ...] = ()) -> None:
        """``args``: more command-line options (``--console PORT``); ``env``: more
        environment variables; ``prefix``: what the command runs under (``ip netns exec
        NAME`` for a server on a host of its own)."""
        self.endpoint = free_local_endpoint()
        self.folder = folder
        config = dict(config or {})
        cfg = {"bus": {"mode": "router", "listen": [self.endpoint], "connect": [],
                       **config.pop("bus", {})},
               "out": str(folder / "server"), **config}
        (folder / "server.yaml").write_text(yaml.safe_dump(cfg))
        self.log_path = folder / "server.log"
        self._log = open(self.log_path, "wb")  # noqa: SIM115 (closed in stop)
        self.proc = subprocess.Popen(
            [*prefix, sys.executable, "-m", "mrslam", "server", "-c", str(folder / "server.yaml"),
             *args], cwd=ROOT, stdout=self._log, stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})})

    def client(self, timeout_s: float = 60.0) -> Bus:
        """A client session, once the server is up (its liveliness token seen)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                bus = Bus.open("client", connect=[self.endpoint])
                break
            except BusError:
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    raise
                time.sleep(0.2)
        seen = threading.Event()
        bus.watch_alive(keys.SERVER_ALIVE, lambda _k, alive: alive and seen.set())
        if not seen.wait(max(1.0, deadline - time.monotonic())):
            bus.close()
            raise BusError("the server's liveliness token never appeared")
        return bus

    def log_lines(self) -> list[str]:
        return self.log_path.read_text(errors="replace").splitlines()

    def stop(self) -> int:
        """SIGTERM (the server writes its outputs), then its exit code."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self._log.closed:
            self._log.close()
        return int(self.proc.returncode)


def room_scan(robot_id: str, seq: int, stamp_ns: int, t_s: float, beams: int = 360) -> Scan:
    """A scan from a robot circling slowly in an 8 m × 6 m room, with its odometry."""
    x, y = 4.0 + 1.5 * np.cos(0.05 * t_s), 3.0 + 1.5 * np.sin(0.05 * t_s)
    th = float(np.angle(np.exp(1j * (0.05 * t_s + np.pi / 2))))
    a = -np.pi + 2 * np.pi * np.arange(beams) / beams + th
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (8.0 - x) / c, -x / c)
        ty = np.where(s > 0, (6.0 - y) / s, -y / s)
    ranges = np.minimum(np.abs(tx), np.abs(ty))
    return Scan(robot_id=robot_id, seq=seq, stamp_ns=stamp_ns, odom_pose=(float(x), float(y), th),
                angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / beams,
                range_min_mm=50, range_max_mm=12000,
                ranges_mm=quantise_ranges_mm(ranges, 0.05, 12.0))


class RoomRobot:
    """A robot on the wire: token, 10 Hz scans by its own clock, commands counted."""

    def __init__(self, endpoint: str, robot_id: str, token: bool = True) -> None:
        self.robot_id = robot_id
        self.bus = Bus.open("client", connect=[endpoint])
        self.clock_offset_ns = 0          # the robot's clock minus the true time
        self.sent: dict[int, float] = {}  # own stamp -> monotonic time sent
        self.commands: list[tuple[float, VelocityCommand]] = []  # (monotonic time, command)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.bus.subscribe(keys.robot_cmd_vel(robot_id), VelocityCommand, self._on_cmd)
        if token:
            self.bus.declare_alive(keys.robot_alive(robot_id))
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _on_cmd(self, _key: str, cmd: VelocityCommand) -> None:
        with self._lock:
            self.commands.append((time.monotonic(), cmd))

    def start(self) -> RoomRobot:
        self._thread.start()
        return self

    def _run(self) -> None:
        seq, t0 = 0, time.monotonic()
        while not self._stop.wait(max(0.0, t0 + 0.1 * seq - time.monotonic())):
            stamp = time.time_ns() + self.clock_offset_ns
            self.sent[stamp] = time.monotonic()
            self.bus.publish(keys.robot_scan(self.robot_id),
                             room_scan(self.robot_id, seq, stamp, 0.1 * seq))
            seq += 1

    def answered_since(self, t_mono: float) -> int:
        """Commands received after ``t_mono`` that answer a scan this robot sent."""
        with self._lock:
            return sum(1 for t, c in self.commands if t >= t_mono and c.stamp_ns in self.sent)

    def longest_silence_s(self, since: float, until: float) -> float:
        """The longest time between answered commands (or the window's ends) in a window."""
        with self._lock:
            times = [t for t, c in self.commands if since <= t <= until and
                     c.stamp_ns in self.sent]
        edges = [since, *times, until]
        return max(b - a for a, b in itertools.pairwise(edges))

    def answered_within(self, since: float, until: float, limit_s: float = 1.0) -> float:
        """The share of the scans sent in [since, until] (monotonic) that got their command
        within ``limit_s``."""
        with self._lock:
            first = {}
            for t, c in self.commands:
                first.setdefault(c.stamp_ns, t)
        sent = [(stamp, t) for stamp, t in list(self.sent.items()) if since <= t <= until]
        if not sent:
            return 0.0
        ok = sum(1 for stamp, t in sent if stamp in first and first[stamp] - t <= limit_s)
        return ok / len(sent)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.bus.close()
