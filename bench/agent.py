"""The agent's cost on the robot: CPU share of one core and resident memory; prints JSON.

The agent runs as its own process (``mrslam agent``) with the hardware backend. Its devices are
played by this process on pseudo-terminals: an RPLIDAR streaming 10 revolutions/s of
``--nodes`` standard scan nodes each (an A2M8 gives ~400 at 10 Hz) and the base's
microcontroller reporting encoders at 50 Hz. This process is also the server: a router session
on loopback that declares its liveliness, receives the scans and sends a velocity command with
every scan, as the server's controller does. After ``--warmup-s`` the agent's CPU time
(/proc/<pid>/stat utime + stime) is measured over ``--seconds``; its RSS is read at the end.
The camera is off (no capture device here); ArUco detection costs extra per decoded frame.

    python bench/agent.py [--seconds 20] [--warmup-s 5] [--nodes 400]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from robot_agent.drivers.fakes.base import FakeMicrocontroller  # noqa: E402
from robot_agent.drivers.fakes.rplidar import FakeRplidar, wall_room_mm  # noqa: E402
from schemas import Scan, VelocityCommand, keys  # noqa: E402
from schemas.bus import Bus, free_local_endpoint  # noqa: E402


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--warmup-s", type=float, default=5.0)
    ap.add_argument("--nodes", type=int, default=400, help="scan nodes per revolution")
    a = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="mrslam-bench-agent-"))
    endpoint = free_local_endpoint()
    lidar = FakeRplidar(tmp / "rplidar", wall_room_mm(2500.0), nodes_per_rev=a.nodes)
    mcu = FakeMicrocontroller(tmp / "base")
    cfg = {"robot_id": "r1", "backend": "hardware", "bus": {"connect": [endpoint]},
           "hardware": {"lidar": {"port": str(lidar.link)}, "base": {"port": str(mcu.link)},
                        "camera": {"enabled": False}}}
    (tmp / "agent.yaml").write_text(yaml.safe_dump(cfg))
    scans: list[int] = []
    with Bus.open("router", listen=[endpoint]) as server:
        server.declare_alive(keys.SERVER_ALIVE)

        def on_scan(key: str, msg: Scan) -> None:
            scans.append(time.monotonic_ns())
            server.publish(keys.robot_cmd_vel("r1"), VelocityCommand(
                robot_id="r1", seq=msg.seq, stamp_ns=time.time_ns(), v_mps=0.1,
                omega_rps=0.2, ttl_s=0.5))

        server.subscribe(keys.robot_scan("r1"), Scan, on_scan)
        # its log (stderr) into a file: a pipe nobody reads while it runs would fill and stall it
        err_log = (tmp / "agent.log").open("wb")
        proc = subprocess.Popen([sys.executable, "-m", "mrslam.cli", "agent", "-c",
                                 str(tmp / "agent.yaml")], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=err_log)
        try:
            time.sleep(a.warmup_s)
            n0, c0, t0 = len(scans), cpu_seconds(proc.pid), time.monotonic()
            time.sleep(a.seconds)
            n1, c1, t1 = len(scans), cpu_seconds(proc.pid), time.monotonic()
            rss = rss_mb(proc.pid)
            alive = proc.poll() is None
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            err_log.close()
            err = (tmp / "agent.log").read_bytes()
    lidar.close()
    mcu.close()
    cpu_percent = 100.0 * (c1 - c0) / (t1 - t0)
    print(json.dumps({
        "backend": "hardware (pty RPLIDAR + pty microcontroller), camera off",
        "nodes_per_revolution": a.nodes, "seconds": round(t1 - t0, 1),
        "scan_rate_hz": round((n1 - n0) / (t1 - t0), 2),
        "agent_cpu_percent_of_one_core": round(cpu_percent, 2),
        "agent_rss_mb": round(rss, 1),
        "goal": {"cpu_percent": 10.0, "rss_mb": 150.0},
        "meets_goal": cpu_percent <= 10.0 and rss <= 150.0 and alive,
        "agent_ran_throughout": alive,
        **({"agent_stderr_tail": err.decode(errors="replace")[-500:]} if not alive else {}),
    }, indent=2))


if __name__ == "__main__":
    main()
