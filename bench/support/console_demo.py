"""``mrslam demo --console`` as its own process, and a client on its bus that writes down every
velocity command the server sends and every velocity the simulator reports, with the wall
time it saw each; for the console's benchmark and its end-to-end test."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import yaml

from schemas import SimClock, SimOdometry, VelocityCommand, keys
from schemas.bus import Bus, BusError
from server.console.service import TOKEN_ENV

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "console-bench-token-0123456789"

#: one velocity seen: (wall time [s], robot, v [m/s], ω [rad/s])
Sample = tuple[float, str, float, float]


class DemoDidNotStart(RuntimeError):
    """The demo ended, or its server did not come up, before it ran (e.g. its monitor gave
    up waiting for a server slow to start on a loaded machine)."""


class DemoRun:
    """``mrslam demo --no-record --out RUN [--console PORT]`` with a known token."""

    def __init__(self, run: Path, console_port: int | None, *args: str) -> None:
        self.run = run
        self.console_port = console_port
        cmd = [sys.executable, "-m", "mrslam", "demo", "--no-record", "--out", str(run),
               *(["--console", str(console_port)] if console_port is not None else []), *args]
        shutil.rmtree(run, ignore_errors=True)       # a run tried before in its place
        run.parent.mkdir(parents=True, exist_ok=True)
        self._log = (run.parent / f"{run.name}.log").open("wb")
        self.t0 = time.monotonic()
        self.wall_s = 0.0
        self.proc = subprocess.Popen(cmd, cwd=ROOT, stdout=self._log, stderr=subprocess.STDOUT,
                                     env={**os.environ, "PYTHONPATH": str(ROOT),
                                          TOKEN_ENV: TOKEN})

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.console_port}/?token={TOKEN}"

    def watch(self, timeout_s: float = 120.0) -> Watch:
        """A ``Watch`` on the demo's bus once its server (and its console) is up."""
        deadline = time.monotonic() + timeout_s
        while self.proc.poll() is None and time.monotonic() < deadline:
            try:
                cfg = yaml.safe_load((self.run / "server.yaml").read_text())
                watch = Watch(cfg["bus"]["listen"][0])
                if self.console_port is not None:
                    try:
                        self.wait_console(max(1.0, deadline - time.monotonic()))
                    except DemoDidNotStart:
                        watch.close()
                        raise
                return watch
            except (OSError, TypeError, KeyError, BusError):   # not written or not up yet
                time.sleep(0.5)
        self.stop()
        raise DemoDidNotStart(f"the demo's server never came up ({self.run})")

    def wait_console(self, timeout_s: float = 120.0) -> None:
        """Wait until the console answers (the server listens on the bus a moment before:
        it opens its console once its state is loaded)."""
        deadline = time.monotonic() + timeout_s
        while self.proc.poll() is None and time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"{self.url.replace('/?', '/state?')}",
                                            timeout=5) as r:
                    if r.status == 200:
                        return
            except OSError:
                pass
            time.sleep(0.5)
        self.stop()
        raise DemoDidNotStart(f"the demo's console never answered ({self.run})")

    def stop(self) -> None:
        """Interrupt a demo still running, as Ctrl-C would (it stops its processes)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=90)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self._log.closed:
            self._log.close()

    def wait(self, timeout_s: float = 1800.0) -> int:
        try:
            self.proc.wait(timeout=timeout_s)
        finally:
            self.stop()
        self.wall_s = time.monotonic() - self.t0
        return int(self.proc.returncode)


class Watch:
    """What the bus shows: commands to the robots, the simulator's velocities, its clock."""

    def __init__(self, endpoint: str) -> None:
        self.sim_time_s = 0.0
        self.commands: list[Sample] = []
        self.sim_velocities: list[Sample] = []
        self._lock = threading.Lock()
        self.bus = Bus.open("client", connect=[endpoint], connect_timeout_ms=10000)
        self.bus.subscribe(keys.SIM_CLOCK, SimClock, self._on_clock)
        self.bus.subscribe(f"{keys.ROOT}/robot/*/cmd_vel", VelocityCommand, self._on_command)
        self.bus.subscribe(f"{keys.ROOT}/sim/robot/*/odom", SimOdometry, self._on_odom)

    def _on_clock(self, _key: str, msg: SimClock) -> None:
        self.sim_time_s = msg.stamp_ns * 1e-9

    def _on_command(self, _key: str, msg: VelocityCommand) -> None:
        with self._lock:
            self.commands.append((time.time(), msg.robot_id, msg.v_mps, msg.omega_rps))

    def _on_odom(self, _key: str, msg: SimOdometry) -> None:
        with self._lock:
            self.sim_velocities.append((time.time(), msg.robot_id, msg.v_mps, msg.omega_rps))

    def samples(self, which: str, since: float, until: float = float("inf")) -> list[Sample]:
        with self._lock:
            rows = self.commands if which == "commands" else self.sim_velocities
            return [s for s in rows if since <= s[0] <= until]

    def close(self) -> None:
        self.bus.close()


def moving(s: Sample) -> bool:
    return abs(s[2]) > 1e-9 or abs(s[3]) > 1e-9


def zero_after(samples: list[Sample], robots: list[str], t_from: float,
               t_until: float) -> dict[str, Any]:
    """Per robot, how long after ``t_from`` its velocities went to zero and stayed there up
    to ``t_until`` (its last non-zero sample there, then the zero one after it); None for a
    robot that had no zero sample or was never still to the end."""
    out: dict[str, Any] = {}
    for rid in robots:
        mine = [s for s in samples if s[1] == rid and t_from <= s[0] <= t_until]
        last_moving = max((s[0] for s in mine if moving(s)), default=None)
        after = [s[0] for s in mine if not moving(s) and (last_moving is None
                                                          or s[0] > last_moving)]
        out[rid] = None if not after else round(after[0] - t_from, 3)
    return out


def first_moving_after(samples: list[Sample], t_from: float) -> float | None:
    return next((round(s[0] - t_from, 3) for s in samples if s[0] >= t_from and moving(s)),
                None)
