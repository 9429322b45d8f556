"""Sections of ``bench/hostile.py`` that attack the bus, the robots' commands and the CLI.

- ``payloads``: a real ``mrslam server`` gets 3,000 garbage payloads of 2 MB, half on keys it
  subscribes to (robots' scans and tags), half on keys nobody does. How much does its memory
  grow (goal ≤ 50 MB), and is it still up? ``--uncapped`` runs the same against a server
  whose message cap is lifted to Zenoh's 1 GiB, for comparison.
- ``stranger``: a default server is not reached from this machine's network address; a config
  listening on every interface is refused; against a server that listens there anyway
  (``--insecure``), a stranger's 50 Hz velocity commands to a real agent are all ignored.
- ``bad_inputs``: every bad input × command of ``bench/support/bad_inputs.py``: exit code and stderr
  lines of each (goal: 2 and one line, every time).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import yaml

from bench.support.bad_inputs import cases, run, write_files
from bench.support.fleet import rss_mb
from bench.support.netsec import connect, free_port, primary_ip, start_server, stop, wait_up
from schemas import VelocityCommand, keys
from schemas.bus import DEFAULT_MAX_MESSAGE_SIZE, Bus

ROOT = Path(__file__).resolve().parent.parent
GOAL_GROWTH_MB = 50.0

#: the largest cap the config allows (the comparison run, "uncapped")
UNCAPPED = 1 << 30


def _peak_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return 0.0


def payloads(folder: Path, n: int = 3000, size: int = 2_000_000,
             uncapped: bool = False) -> dict[str, Any]:
    import zenoh

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cap = UNCAPPED if uncapped else DEFAULT_MAX_MESSAGE_SIZE
    cfg = {"bus": {"mode": "router", "listen": [endpoint], "connect": [],
                   "max_message_size": cap},
           "explore": {"total_area_m2": 48.0}, "out": str(folder / "out")}
    (folder / "server.yaml").write_text(yaml.safe_dump(cfg))
    with open(folder / "server.log", "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "mrslam", "server", "-c",
                                 str(folder / "server.yaml")], cwd=ROOT, stdout=log,
                                stderr=log, env={**os.environ, "PYTHONPATH": str(ROOT)})
    garbage = os.urandom(size)
    try:
        with wait_up(endpoint, proc) as bus:
            bus.wait_for_subscribers(keys.robot_scan("r1"), 10.0)
            time.sleep(1.0)
            rss0 = rss_mb(proc.pid)
            targets = [keys.robot_scan("r1"), keys.robot_tags("r2"), "mrslam/nobody/a",
                       "junk/nobody/b"]
            t0 = time.monotonic()
            series = []            # RSS every sixth of the way: flat, or growing?
            for i in range(n):
                bus.session.put(targets[i % len(targets)], garbage,
                                congestion_control=zenoh.CongestionControl.BLOCK)
                if (i + 1) % max(1, n // 6) == 0:
                    series.append(round(rss_mb(proc.pid), 1))
            send_s = time.monotonic() - t0
            time.sleep(2.0)
            rss1, peak = rss_mb(proc.pid), _peak_mb(proc.pid)
            alive: list[bool] = []
            bus.watch_alive(keys.SERVER_ALIVE, lambda _k, up: alive.append(up))
            time.sleep(0.5)
    finally:
        code = stop(proc)
    log_text = (folder / "server.log").read_text(errors="replace")
    summary_file = folder / "out" / "summary.json"
    bus_stats = json.loads(summary_file.read_text())["bus"] if summary_file.exists() else {}
    growth = rss1 - rss0
    return {"messages": n, "bytes_each": size, "cap_bytes": cap, "send_s": round(send_s, 1),
            "rss_before_mb": round(rss0, 1), "rss_after_mb": round(rss1, 1),
            "growth_mb": round(growth, 1), "peak_rss_mb": round(peak, 1),
            "rss_every_sixth_mb": series,
            "rejected_by_the_server": bus_stats.get("rejected", {}),
            "decoded_by_the_server": bus_stats.get("received", {}),
            "server_alive_after": bool(alive and alive[-1]), "exit_code": code,
            "tracebacks": log_text.count("Traceback"),
            "goal_met": growth <= GOAL_GROWTH_MB and bool(alive and alive[-1])}


def payloads_uncapped(folder: Path) -> dict[str, Any]:
    return payloads(folder, uncapped=True)


# -- a stranger on the network ----------------------------------------------------------------
class _StillBase:
    def __init__(self) -> None:
        self.velocities: list[tuple[float, float]] = []

    def odometry_at(self, stamp_ns: int) -> Any:
        return None

    def set_velocity(self, v_mps: float, omega_rps: float) -> None:
        self.velocities.append((v_mps, omega_rps))


class _NoLidar:
    def start(self, on_sweep: Any) -> None:
        pass


def stranger(folder: Path, seconds: float = 5.0) -> dict[str, Any]:
    from robot_agent.backend import Backend
    from robot_agent.config import AgentConfig
    from robot_agent.runtime import Agent

    host = primary_ip()
    out: dict[str, Any] = {"host": host}
    port = free_port()
    # 1. the default bus (but for the port): loopback only
    proc = start_server(folder / "default", {"mode": "router", "connect": [],
                                             "listen": [f"tcp/127.0.0.1:{port}"]})
    try:
        with wait_up(f"tcp/127.0.0.1:{port}", proc):
            reached = connect(f"tcp/{host}:{port}") if host else None
            out["default_server_reached_from_network"] = reached is not None
            if reached is not None:
                reached.close()
    finally:
        stop(proc)
    # 2. every interface, no TLS, no access rules, no --insecure: refused
    open_bus = {"mode": "router", "connect": [], "listen": [f"tcp/0.0.0.0:{port}"]}
    proc = start_server(folder / "refused", open_bus)
    out["open_listen_exit_code"] = proc.wait(timeout=120)
    lines = [ln for ln in (folder / "refused" / "server.log").read_text().splitlines()
             if ln.strip()]
    out["open_listen_stderr_lines"] = len(lines)
    # 3. --insecure: reachable, warned; a stranger's commands to a real agent are ignored
    proc = start_server(folder / "insecure", open_bus, "--insecure")
    base = _StillBase()
    halt = threading.Event()
    sent, bound, counters = 0, False, {}
    try:
        with wait_up(f"tcp/127.0.0.1:{port}", proc) as agent_bus:
            cfg = AgentConfig.model_validate({"robot_id": "r1",
                                              "detector": {"enabled": False}})
            agent = Agent(cfg, agent_bus, Backend(lidar=_NoLidar(), base=base, camera=None,
                                                  now_ns=time.time_ns))
            agent.start()
            loop = threading.Thread(target=agent.run, args=(halt,))
            loop.start()
            deadline = time.monotonic() + 10.0
            while agent.gate.server is None and time.monotonic() < deadline:
                time.sleep(0.05)
            who = f"tcp/{host}:{port}" if host else f"tcp/127.0.0.1:{port}"
            with Bus.open("client", connect=[who]) as evil:
                key = keys.robot_cmd_vel("r1")
                evil.wait_for_subscribers(key, 10.0)
                t0 = time.monotonic()
                while time.monotonic() - t0 < seconds:   # 50 Hz, stamped like the server
                    evil.publish(key, VelocityCommand(robot_id="r1", seq=sent,
                                                      stamp_ns=time.time_ns(), v_mps=0.5,
                                                      omega_rps=2.0, ttl_s=0.5))
                    sent += 1
                    time.sleep(0.02)
                time.sleep(1.0)
            halt.set()
            loop.join(timeout=10)
            counters = dict(agent.counters)
            bound = agent.gate.server is not None
    finally:
        halt.set()
        stop(proc)
    log_text = (folder / "insecure" / "server.log").read_text()
    obeyed = sum(1 for v, _ in base.velocities if v != 0.0)
    ignored = counters.get("commands_ignored", 0)
    out.update({"insecure_warned": "without TLS" in log_text and "WARNING" in log_text,
                "agent_bound_to_server": bound,
                "stranger_commands_sent": sent, "stranger_commands_ignored": ignored,
                "ignored_by_reason": {k.removeprefix("commands_ignored_"): v
                                      for k, v in counters.items()
                                      if k.startswith("commands_ignored_")},
                "stranger_commands_obeyed": obeyed})
    out["goal_met"] = (not out["default_server_reached_from_network"] and host is not None
                       and out["open_listen_exit_code"] == 2
                       and out["open_listen_stderr_lines"] == 1 and out["insecure_warned"]
                       and bound and obeyed == 0 and ignored == sent)
    return out


# -- the command line -------------------------------------------------------------------------
def bad_inputs(folder: Path) -> dict[str, Any]:
    write_files(folder)
    results: dict[str, Any] = {}
    for case in cases(folder):
        o = run(case)
        results[case.id] = {"exit_code": o.code, "stderr_lines": len(o.stderr_lines),
                            "names_it": o.one_line_naming(case.says)}
    bad = [k for k, r in results.items() if not r["names_it"]]
    return {"cases": len(results), "failing": bad, "results": results, "goal_met": not bad}


SECTIONS = {"payloads": payloads, "payloads_uncapped": payloads_uncapped,
            "stranger": stranger, "bad_inputs": bad_inputs}

