"""The recorder's cost: CPU share of one core and bytes written per robot per second; prints JSON.

This process is the bus: a router session on loopback, with ``--robots`` simulated robots
publishing what a run carries per robot — 10 Hz scans of ``--beams`` beams (a room seen with
±1 cm noise while the robot drives), the server's 10 Hz velocity commands, tag detections at the
camera's 5 Hz and a status every second — plus the server's robot states at 4 Hz. ``mrslam record``
runs as its own process. After ``--warmup-s`` its CPU time (/proc/<pid>/stat utime + stime) and
the growth of its file (flushed every second) are measured over ``--seconds``, once per chunk
compression in ``--compression``.

    python bench/record.py [--robots 3] [--seconds 20] [--compression none,zstd]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from recording.reader import read_recording  # noqa: E402
from schemas import (  # noqa: E402
    RobotEstimate,
    RobotStates,
    RobotStatus,
    Scan,
    TagDetection,
    TagDetections,
    VelocityCommand,
    keys,
    quantise_ranges_mm,
)
from schemas.bus import Bus, free_local_endpoint  # noqa: E402
from schemas.se2 import wrap_angle  # noqa: E402

GOAL_CPU_PERCENT, GOAL_BYTES_PER_S = 5.0, 20_000.0


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def room_ranges_m(x: float, y: float, theta: float, angles: np.ndarray,
                  rng: np.random.Generator) -> np.ndarray:
    """Ranges from (x, y, theta) to the walls of a 8 m x 6 m room, with 1 cm noise."""
    a = angles + theta
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (8.0 - x) / c, -x / c)
        ty = np.where(s > 0, (6.0 - y) / s, -y / s)
    r = np.minimum(np.abs(tx), np.abs(ty)) + rng.normal(0.0, 0.01, a.size)
    r[rng.random(a.size) < 0.03] = np.inf  # dropouts
    return r


def publish_robots(bus: Bus, robots: list[str], beams: int, stop: threading.Event) -> None:
    rng = np.random.default_rng(0)
    angles = -np.pi + 2 * np.pi * np.arange(beams) / beams
    k, t0 = 0, time.monotonic()
    while not stop.is_set():
        stamp = time.time_ns()
        poses = []
        for i, rid in enumerate(robots):
            x, y = 4.0 + 2 * float(np.cos(0.02 * k + i)), 3.0 + 2 * float(np.sin(0.02 * k + i))
            th = wrap_angle(0.02 * k)
            poses.append(RobotEstimate(robot_id=rid, team_id=f"team-{rid}", pose=(x, y, th)))
            ranges = room_ranges_m(x, y, th, angles, rng)
            bus.publish(keys.robot_scan(rid), Scan(
                robot_id=rid, seq=k, stamp_ns=stamp, odom_pose=(x, y, th),
                angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / beams, range_min_mm=150,
                range_max_mm=12000, ranges_mm=quantise_ranges_mm(ranges, 0.15, 12.0)))
            bus.publish(keys.robot_cmd_vel(rid), VelocityCommand(
                robot_id=rid, seq=k, stamp_ns=stamp, v_mps=0.3, omega_rps=0.1))
            if k % 2 == 0:
                bus.publish(keys.robot_tags(rid), TagDetections(
                    robot_id=rid, seq=k, stamp_ns=stamp, detections=[TagDetection(
                        tag_id=i + 1, observed_robot_id=robots[(i + 1) % len(robots)],
                        range_m=2.0, bearing_rad=0.2, yaw_rad=1.0, sigma_range_m=0.03,
                        sigma_bearing_rad=0.01, sigma_yaw_rad=0.05)]))
            if k % 10 == 0:
                bus.publish(keys.robot_status(rid), RobotStatus(
                    robot_id=rid, seq=k, stamp_ns=stamp, state="ok", cpu_percent=5.0,
                    rss_mb=80.0, scans_sent=k))
        if k % 3 == 0:
            bus.publish(keys.SERVER_ROBOTS, RobotStates(seq=k, stamp_ns=stamp, robots=poses))
        k += 1
        stop.wait(max(0.0, t0 + 0.1 * k - time.monotonic()))


def measure(endpoint: str, out: Path, compression: str, n_robots: int, warmup_s: float,
            seconds: float) -> dict[str, object]:
    proc = subprocess.Popen([sys.executable, "-m", "mrslam", "record", "--out", str(out),
                             "--connect", endpoint, "--compression", compression], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while not out.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        time.sleep(warmup_s)
        c0, s0, t0 = cpu_seconds(proc.pid), out.stat().st_size, time.monotonic()
        time.sleep(seconds)
        c1, s1, t1 = cpu_seconds(proc.pid), out.stat().st_size, time.monotonic()
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    cpu = 100.0 * (c1 - c0) / (t1 - t0)
    per_robot = (s1 - s0) / (t1 - t0) / n_robots
    report = read_recording(out).report
    return {"compression": compression, "recorder_cpu_percent_of_one_core": round(cpu, 2),
            "bytes_per_s_per_robot": round(per_robot), "file_bytes": out.stat().st_size,
            "messages": report.messages, "file_intact": report.intact, "exit_code": code,
            "meets_goal": cpu <= GOAL_CPU_PERCENT and per_robot <= GOAL_BYTES_PER_S
            and report.messages > 0 and report.intact and code == 0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--beams", type=int, default=400)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--warmup-s", type=float, default=3.0)
    ap.add_argument("--compression", default="none,zstd", help="comma-separated: none,zstd,lz4")
    a = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="mrslam-bench-record-"))
    endpoint = free_local_endpoint()
    robots = [f"r{i + 1}" for i in range(a.robots)]
    runs = []
    with Bus.open("router", listen=[endpoint]) as bus:
        stop = threading.Event()
        pub = threading.Thread(target=publish_robots, args=(bus, robots, a.beams, stop),
                               daemon=True)
        pub.start()
        for comp in a.compression.split(","):
            runs.append(measure(endpoint, tmp / f"{comp}.mcap", comp, a.robots, a.warmup_s,
                                a.seconds))
        stop.set()
        pub.join(timeout=5)
    print(json.dumps({
        "robots": a.robots, "beams": a.beams, "scan_hz": 10, "seconds": a.seconds,
        "runs": runs,
        "goal": {"cpu_percent": GOAL_CPU_PERCENT, "bytes_per_s_per_robot": GOAL_BYTES_PER_S},
        "meets_goal": all(bool(r["meets_goal"]) for r in runs),
    }, indent=2))


if __name__ == "__main__":
    main()
