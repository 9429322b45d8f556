"""Watching a run from the outside, as any Zenoh client can: progress, events, wire bytes."""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from typing import Any

from mrslam.launch import Proc
from mrslam.supervise import Exit, Supervisor
from schemas import Event, RobotStates, SimClock, keys
from schemas.bus import Bus, BusError

#: commands that come after this long without any [s] start a new stretch of them
COMMAND_PAUSE_S = 0.5


class Stopped(Exception):
    """The run was asked to stop before the monitor was on the bus."""


class Monitor:
    def __init__(self, endpoint: str, robots: list[str],
                 stop: threading.Event | None = None, timeout_s: float = 60.0) -> None:
        """Connects to the server at ``endpoint``: it was just started, and on a loaded
        machine it may take a while to listen (``timeout_s``); tries again every second, so
        that a ``stop`` set meanwhile ends the wait (``Stopped``)."""
        stop = stop or threading.Event()
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.bus = Bus.open("client", connect=[endpoint], connect_timeout_ms=1000)
                break
            except BusError:
                if stop.is_set():
                    raise Stopped("stopped before the server was up") from None
                if time.monotonic() > deadline:
                    raise
                stop.wait(0.1)
        self.stop = stop
        self.robots = robots
        self.sim_time_s = 0.0
        self.states: RobotStates | None = None
        self.events: list[Event] = []
        self.bytes_sent: Counter[str] = Counter()
        self.messages_sent: Counter[str] = Counter()
        self._server_up = threading.Event()
        # for the server's restarts, all on time.monotonic(): when its liveliness token came
        # (back), each team-coverage figure it sent, and the first command after each pause
        self.server_up_at: list[float] = []
        self.server_alive = False
        self.coverage_at: list[tuple[float, float]] = []
        self.commands_resumed_at: list[float] = []
        self._last_command_at = -1.0
        self._lock = threading.Lock()
        self.bus.watch_alive(keys.SERVER_ALIVE, self._on_server)
        self.bus.subscribe(keys.SIM_CLOCK, SimClock, self._on_clock)
        self.bus.subscribe(keys.SERVER_ROBOTS, RobotStates, self._on_states)
        self.bus.subscribe(keys.SERVER_EVENTS, Event, self._on_event)
        self.bus.subscribe_raw(f"{keys.ROOT}/robot/*/*", self._on_robot_bytes)

    def _on_server(self, key: str, alive: bool) -> None:
        self.server_alive = alive
        if alive:
            self._server_up.set()
            with self._lock:
                self.server_up_at.append(time.monotonic())

    def _on_clock(self, key: str, msg: SimClock) -> None:
        self.sim_time_s = msg.stamp_ns * 1e-9

    def _on_states(self, key: str, msg: RobotStates) -> None:
        self.states = msg
        with self._lock:
            self.coverage_at.append((time.monotonic(), self.coverage()))

    def _on_event(self, key: str, msg: Event) -> None:
        with self._lock:
            self.events.append(msg)

    def _on_robot_bytes(self, key: str, payload: bytes) -> None:
        rid = keys.robot_id_of(key)
        if key.endswith("/cmd_vel"):
            now = time.monotonic()
            with self._lock:
                if now - self._last_command_at > COMMAND_PAUSE_S:
                    self.commands_resumed_at.append(now)
                self._last_command_at = now
        elif rid is not None:  # what the robot sends
            with self._lock:
                self.bytes_sent[rid] += len(payload)
                self.messages_sent[rid] += 1

    def wait_for_server(self, timeout_s: float, alive: Any) -> bool:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if self._server_up.wait(0.2):
                return True
            if not alive() or self.stop.is_set():
                return False
        return False

    def coverage(self) -> float:
        s = self.states
        return max((t.coverage for t in s.teams), default=0.0) if s else 0.0

    def follow(self, server: Supervisor, sim: Proc, wall_timeout_s: float, threshold: float,
               console: Any, progress: bool) -> str:
        """Block until the run ends; returns why: finished, sim-ended, server-died, timeout,
        stopped (the monitor's ``stop`` was set: a signal). A server that dies is restarted
        by ``server`` while the run goes on. The progress bar's last line says how it ended."""
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        columns = [TextColumn("[bold]coverage"), BarColumn(), TextColumn("{task.fields[cov]}"),
                   TextColumn("sim {task.fields[sim]}"), TextColumn("{task.fields[robots]}"),
                   TimeElapsedColumn()]
        t0 = time.monotonic()
        with Progress(*columns, console=console, disable=not progress, transient=False) as bar:
            task = bar.add_task("run", total=threshold, cov="0.0%", sim="0 s", robots="")
            while True:
                # a stop signal is heeded before the server is polled (which may restart it)
                state = None if self.stop.is_set() else server.poll(self.sim_time_s)
                why = self._ended(state, sim, time.monotonic() - t0 > wall_timeout_s)
                cov = self.coverage()
                bar.update(task, completed=min(cov, threshold), cov=f"{cov:.1%}",
                           sim=f"{self.sim_time_s:.0f} s",
                           robots=self._status(state, why, server.restarts, wall_timeout_s))
                if why is not None:
                    return why
                self.stop.wait(0.25)

    def _ended(self, state: str | None, sim: Proc, timed_out: bool) -> str | None:
        """Why the run is over (see ``follow``), or None while it goes on."""
        if state is None:
            return "stopped"
        if state == "done":
            return "finished"
        if state == "failed":
            return "server-died"
        if not sim.alive():
            return "sim-ended"
        return "timeout" if timed_out else None

    def _status(self, state: str | None, why: str | None, restarts: int,
                wall_timeout_s: float) -> str:
        """The bar's last column: the robots' modes while the run goes on, then its end."""
        robots = self._robot_line()
        if why == "finished":
            return f"run finished: {robots}"
        if why == "server-died":
            return f"run ended: the server died for good ({restarts} restart(s) spent)"
        if why == "sim-ended":
            return f"run ended: the simulator stopped first; {robots}"
        if why == "timeout":
            return f"run given up after {wall_timeout_s:.0f} s wall; {robots}"
        if why == "stopped":
            return "run stopped"
        if state == "restarting":
            return f"server restarting ({restarts} so far)"
        return robots

    def _robot_line(self) -> str:
        s = self.states
        if s is None:
            return "waiting for robots"
        return " ".join(f"{r.robot_id}:{r.mode}" for r in s.robots)

    def recovery(self, ex: Exit) -> dict[str, Any]:
        """What the bus showed around a restart of the server: the team coverage it last sent
        before ``ex`` and first sent after the restart, and how long after the restart its
        liveliness token came back and its first command reached a robot [s]."""
        start = ex.restarted_at if ex.restarted_at is not None else math.inf   # never
        with self._lock:
            before = [c for t, c in self.coverage_at if t <= ex.exited_at]
            after = [c for t, c in self.coverage_at if t > start]
            up = [t for t in self.server_up_at if t > start]
            cmd = [t for t in self.commands_resumed_at if t > start]
        return {"coverage_before": before[-1] if before else None,
                "coverage_after": after[0] if after else None,
                "up_after_s": round(up[0] - start, 3) if up else None,
                "first_command_after_s": round(cmd[0] - start, 3) if cmd else None}

    def results(self) -> dict[str, Any]:
        with self._lock:
            return {"bytes_sent": dict(self.bytes_sent),
                    "messages_sent": dict(self.messages_sent),
                    "events": [{"kind": e.kind, "stamp_ns": e.stamp_ns, "robot_ids": e.robot_ids,
                                "message": e.message} for e in self.events],
                    "sim_time_s": self.sim_time_s,
                    "bus": self.bus.stats.as_dict()}

    def close(self) -> None:
        self.bus.close()

    def __enter__(self) -> Monitor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
