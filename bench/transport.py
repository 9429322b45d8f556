"""Scan transport between two processes on loopback; prints JSON.

Process A is the server side (router session, decodes every scan), process B an agent-side
client that encodes and publishes 400-beam scans:

- burst: B publishes as fast as it can (congestion control BLOCK, so nothing is dropped);
  throughput = scans decoded by A per second.
- steady: 20 robots x 10 Hz = 200 scans/s for ``--steady-s`` seconds; latency = A's decode time
  minus the ``stamp_ns`` B set just before encoding (same clock, same machine).

    python bench/transport.py [--burst N] [--steady-s S]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

from schemas import Scan, decode, encode, keys, quantise_ranges_mm
from schemas.bus import Bus, free_local_endpoint

BEAMS = 400


def make_scan(robot_id: str, seq: int, ranges_mm: bytes) -> Scan:
    return Scan(robot_id=robot_id, seq=seq, stamp_ns=time.time_ns(),
                odom_pose=(12.5, -3.25, 1.2), angle_min_rad=-np.pi,
                angle_increment_rad=2 * np.pi / BEAMS, range_min_mm=50, range_max_mm=10000,
                ranges_mm=ranges_mm)


def receiver(endpoint: str, expected: int, skip: int, timeout_s: float) -> None:
    lat_ns: list[int] = []
    times: list[int] = []
    skipped = [0]

    def on_scan(key: str, msg: Scan) -> None:
        now = time.time_ns()
        if skipped[0] < skip:  # the messages that declared the publishers
            skipped[0] += 1
            return
        lat_ns.append(now - msg.stamp_ns)
        times.append(now)

    with Bus.open("router", listen=[endpoint]) as bus:
        bus.subscribe(keys.ALL_SCANS, Scan, on_scan)
        print("ready", flush=True)
        t0 = time.monotonic()
        while len(times) < expected and time.monotonic() - t0 < timeout_s:
            time.sleep(0.01)
        lat = np.array(lat_ns, dtype=np.float64) / 1e6
        span_s = (times[-1] - times[0]) / 1e9 if len(times) > 1 else float("nan")
        print(json.dumps({
            "received": len(times), "rejected": sum(bus.stats.rejected.values()),
            "span_s": span_s,
            "p50_ms": float(np.percentile(lat, 50)) if len(lat) else None,
            "p99_ms": float(np.percentile(lat, 99)) if len(lat) else None,
            "max_ms": float(lat.max()) if len(lat) else None,
        }), flush=True)


def sender(endpoint: str, mode: str, n: int, robots: int, rate_hz: float) -> None:
    rng = np.random.default_rng(1)
    ranges = [quantise_ranges_mm(rng.uniform(0.05, 10.0, BEAMS), 0.05, 10.0) for _ in range(8)]
    with Bus.open("client", connect=[endpoint]) as bus:
        rids = [f"r{i + 1}" for i in range(robots)]
        for rid in rids:  # declare publishers before timing starts
            bus.publish(keys.robot_scan(rid), make_scan(rid, 0, ranges[0]), block=True)
        time.sleep(0.5)
        if mode == "burst":
            for i in range(n):
                rid = rids[i % robots]
                bus.publish(keys.robot_scan(rid), make_scan(rid, i, ranges[i % 8]), block=True)
        else:
            period = 1.0 / (rate_hz * robots)
            t_next = time.perf_counter()
            for i in range(n):
                t_next += period
                while (d := t_next - time.perf_counter()) > 0:
                    time.sleep(min(d, 0.002)) if d > 0.0005 else None
                rid = rids[i % robots]
                bus.publish(keys.robot_scan(rid), make_scan(rid, i, ranges[i % 8]), block=True)
        time.sleep(0.5)


def run_pair(mode: str, n: int, robots: int, rate_hz: float) -> dict[str, object]:
    endpoint = free_local_endpoint()
    me = [sys.executable, __file__]
    warm = robots  # the publisher-declaring messages
    rx = subprocess.Popen([*me, "--role", "rx", "--endpoint", endpoint, "--expected", str(n),
                           "--skip", str(warm)], stdout=subprocess.PIPE, text=True)
    assert rx.stdout is not None
    assert rx.stdout.readline().strip() == "ready"
    subprocess.run([*me, "--role", "tx", "--endpoint", endpoint, "--mode", mode, "--n",
                    str(n), "--robots", str(robots), "--rate", str(rate_hz)],
                   check=True)
    out = json.loads(rx.stdout.readline())
    rx.wait(timeout=30)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--role", default="main")
    ap.add_argument("--endpoint")
    ap.add_argument("--expected", type=int, default=0)
    ap.add_argument("--skip", type=int, default=0)
    ap.add_argument("--mode", default="burst")
    ap.add_argument("--n", type=int, default=0)
    ap.add_argument("--robots", type=int, default=20)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--burst", type=int, default=50_000)
    ap.add_argument("--steady-s", type=float, default=15.0)
    a = ap.parse_args()
    if a.role == "rx":
        return receiver(a.endpoint, a.expected, a.skip, timeout_s=120)
    if a.role == "tx":
        return sender(a.endpoint, a.mode, a.n, a.robots, a.rate)

    scan_bytes = len(encode(make_scan("r1", 123456, quantise_ranges_mm(
        np.random.default_rng(0).uniform(0.05, 10.0, BEAMS), 0.05, 10.0))))
    t0 = time.perf_counter()
    for _ in range(20000):
        decode(encode(make_scan("r1", 1, b"\x10\x27" * BEAMS)), Scan)
    codec_us = (time.perf_counter() - t0) / 20000 * 1e6
    burst = run_pair("burst", a.burst, 20, 0.0)
    steady_n = int(a.steady_s * 200)
    steady = run_pair("steady", steady_n, 20, 10.0)
    print(json.dumps({
        "bench": "transport",
        "beams": BEAMS,
        "bytes_per_scan": scan_bytes,
        "encode_decode_us": round(codec_us, 2),
        "burst": {"scans": a.burst, "received": burst["received"],
                  "scans_per_s": round((burst["received"] - 1) / burst["span_s"])},
        "steady_200_per_s": {"scans": steady_n, "received": steady["received"],
                             "p50_ms": round(steady["p50_ms"], 3),
                             "p99_ms": round(steady["p99_ms"], 3),
                             "max_ms": round(steady["max_ms"], 3)},
        "goals": {"bytes_per_scan_max": 1000, "scans_per_s_min": 20000, "p99_ms_max": 5.0},
    }, indent=2))


if __name__ == "__main__":
    main()
