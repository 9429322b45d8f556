"""Load generation for ``bench/load.py``: recorded robot tracks and the processes replaying them.

``make_tracks`` drives the robots of the scenario large-house-5 (the package's own
world, LIDAR and odometry noise) with a simple reactive wanderer for a while and keeps each step's
LIDAR ranges (uint16 mm, as the wire carries them) and wheel odometry. That is done once per bench
run; replaying it costs a struct and an encode per scan.

A generator process (``python -m bench.support.load_gen``) stands in for many robots on one Zenoh
client session. Each robot looks like an agent to the server: its liveliness token
(``mrslam/robot/<id>/alive``, which admits it at once), a subscription to its ``cmd_vel``, and
``Scan`` messages on ``mrslam/robot/<id>/scan`` at 10 Hz with its own id, ``seq`` counting from
0, ``stamp_ns`` from this machine's clock, and the odometry of a track replayed back and forth
(forward, then backward along the same path, so the odometry never jumps) from an offset of its
own. The server answers each scan with a ``VelocityCommand`` carrying the scan's own stamp, which
is how a command is matched to the scan it answers.

The protocol with the parent is one JSON line each way at a time over stdin/stdout:

    parent -> child  {"endpoint", "robots": [[id, track, offset, phase_s]], "tracks", ...}
    child -> parent  {"ready": true}                      (session open, tokens declared)
    parent -> child  {"t_start", "t_measure", "t_end"}   (time.monotonic(), shared by processes)
    child -> parent  {...figures of the measuring window...}
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

TRACK_SCENARIO = "large-house-5"   # the large house, five spawn poses far apart


@dataclass
class Tracks:
    """Recorded robots: ``ranges_mm`` (tracks, steps, beams) uint16, ``odom`` (tracks, steps, 3)."""

    ranges_mm: np.ndarray
    odom: np.ndarray
    angle_min_rad: float
    angle_increment_rad: float
    range_min_mm: int
    range_max_mm: int

    def save(self, path: Path) -> None:
        np.savez(path, ranges_mm=self.ranges_mm, odom=self.odom,
                 lidar=np.array([self.angle_min_rad, self.angle_increment_rad,
                                 self.range_min_mm, self.range_max_mm]))

    @classmethod
    def load(cls, path: Path) -> Tracks:
        with np.load(path) as z:
            lid = z["lidar"]
            return cls(z["ranges_mm"], z["odom"], float(lid[0]), float(lid[1]), int(lid[2]),
                       int(lid[3]))

    @property
    def steps(self) -> int:
        return int(self.ranges_mm.shape[1])


def _wander(ranges: np.ndarray, angles: np.ndarray, state: dict[str, float],
            rng: np.random.Generator) -> tuple[float, float]:
    """A reactive wanderer: ahead toward open space at 0.3 m/s, turning in place (away from
    the nearer side) while something is closer than 0.7 m ahead."""
    r = np.where(np.isfinite(ranges), ranges, 10.0)
    ahead = np.abs(angles) < math.radians(35)
    front = float(r[ahead].min())
    turning = state.get("turn", 0.0)
    if (turning and front < 1.2) or front < 0.7:
        if not turning:
            left = float(r[(angles > 0.3) & (angles < 1.6)].mean())
            right = float(r[(angles < -0.3) & (angles > -1.6)].mean())
            turning = 1.0 if left >= right else -1.0
        state["turn"] = turning
        return 0.0, 1.0 * turning
    state["turn"] = 0.0
    # head for the most open direction within ±60°, with a little noise
    wide = np.abs(angles) < math.radians(60)
    smooth = np.convolve(r, np.ones(15) / 15, mode="same")
    best = float(angles[wide][int(np.argmax(smooth[wide]))])
    return 0.3, float(np.clip(0.8 * best + 0.2 * rng.standard_normal(), -0.8, 0.8))


def make_tracks(steps: int, seed: int = 1) -> Tracks:
    """``steps`` simulated LIDAR periods of the scenario's robots wandering the large house."""
    from schemas import quantise_ranges_mm
    from sim.config import SimConfig
    from sim.process import build

    cfg = SimConfig(scenario=TRACK_SCENARIO, camera={"enabled": False}, seed=seed)
    sim, _ = build(cfg)
    lid = sim.p.lidar
    angles = lid.angle_min_rad + lid.angle_increment_rad * np.arange(lid.beams)
    ids = list(sim.robots)
    ranges = np.zeros((len(ids), steps, lid.beams), dtype="<u2")
    odom = np.zeros((len(ids), steps, 3))
    rng = np.random.default_rng(seed)
    states: dict[str, dict[str, float]] = {rid: {} for rid in ids}
    for k in range(steps):
        obs = sim.sense()
        for i, rid in enumerate(ids):
            ranges[i, k] = np.frombuffer(quantise_ranges_mm(obs.ranges_m[rid], lid.range_min_m,
                                                            lid.range_max_m), dtype="<u2")
            odom[i, k] = obs.odometry[rid][0]
            sim.set_command(rid, *_wander(obs.ranges_m[rid], angles, states[rid], rng))
        sim.advance()
    return Tracks(ranges, odom, lid.angle_min_rad, lid.angle_increment_rad,
                  round(lid.range_min_m * 1000), round(lid.range_max_m * 1000))


def pingpong(k: int, n: int) -> int:
    """Step ``k`` of a walk 0, 1, ..., n-1, n-2, ..., 1, 0, 1, ... over ``n`` recorded steps."""
    if n < 2:
        return 0
    m = k % (2 * n - 2)
    return m if m < n else 2 * n - 2 - m


# -- the generator process ----------------------------------------------------------------------
def _send_loop(bus: Any, robots: list[tuple[str, int, int, float]], tracks: Tracks,
               period_s: float, t_start: float, t_measure: float, t_end: float,
               pending: dict[tuple[str, int], float], lock: threading.Lock
               ) -> tuple[dict[str, int], list[float]]:
    """Publish every robot's scans on its schedule until ``t_end``; returns the scans sent
    in the measuring window per robot, and how late each of those was sent [s]."""
    import msgspec

    from schemas import Scan, keys

    scan_keys = {rid: keys.robot_scan(rid) for rid, *_ in robots}
    blobs = [[tracks.ranges_mm[t, k].tobytes() for k in range(tracks.steps)]
             for t in range(tracks.ranges_mm.shape[0])]
    template = Scan(robot_id=robots[0][0], seq=0, stamp_ns=0, odom_pose=(0.0, 0.0, 0.0),
                    angle_min_rad=tracks.angle_min_rad,
                    angle_increment_rad=tracks.angle_increment_rad,
                    range_min_mm=tracks.range_min_mm, range_max_mm=tracks.range_max_mm,
                    ranges_mm=blobs[0][0])
    order = sorted(robots, key=lambda r: r[3])
    sent: dict[str, int] = {rid: 0 for rid, *_ in robots}
    lateness: list[float] = []
    n = tracks.steps
    k = 0
    while True:
        for rid, track, offset, phase in order:
            due = t_start + k * period_s + phase
            if due >= t_end:
                return sent, lateness
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            i = pingpong(offset + k, n)
            o = tracks.odom[track, i]
            stamp = time.time_ns()
            scan = msgspec.structs.replace(
                template, robot_id=rid, seq=k, stamp_ns=stamp,
                odom_pose=(float(o[0]), float(o[1]), float(o[2])), ranges_mm=blobs[track][i])
            now = time.monotonic()
            if now >= t_measure:
                with lock:
                    pending[(rid, stamp)] = now
                sent[rid] += 1
                lateness.append(now - due)
            bus.publish(scan_keys[rid], scan)
        k += 1


def run_generator(spec: dict[str, Any], timing_line: Any, emit: Any) -> dict[str, Any]:
    from schemas import VelocityCommand, keys
    from schemas.bus import Bus

    tracks = Tracks.load(Path(spec["tracks"]))
    robots = [(str(r[0]), int(r[1]), int(r[2]), float(r[3])) for r in spec["robots"]]
    pending: dict[tuple[str, int], float] = {}      # (robot, stamp) -> monotonic time sent
    answered: dict[tuple[str, int], float] = {}     # (robot, stamp) -> latency [s]
    counts = {"commands": 0, "unmatched": 0}
    lock = threading.Lock()

    def on_cmd(_key: str, cmd: VelocityCommand) -> None:
        t = time.monotonic()
        with lock:
            counts["commands"] += 1
            t0 = pending.pop((cmd.robot_id, cmd.stamp_ns), None)
            if t0 is None:
                counts["unmatched"] += 1   # a warm-up scan's, or not one of ours
            else:
                answered[(cmd.robot_id, cmd.stamp_ns)] = t - t0

    bus = Bus.open("client", connect=[spec["endpoint"]], connect_timeout_ms=30000)
    try:
        for rid, *_ in robots:
            bus.subscribe(keys.robot_cmd_vel(rid), VelocityCommand, on_cmd)
            bus.declare_alive(keys.robot_alive(rid))
        if not bus.wait_for_subscribers(keys.robot_scan(robots[0][0]), 30.0):
            raise RuntimeError("nobody subscribes to the robots' scans")
        emit({"ready": True})
        timing = timing_line()
        measure_ns = time.time_ns() + int((timing["t_measure"] - time.monotonic()) * 1e9)
        cpu0 = time.process_time()
        sent, lateness = _send_loop(bus, robots, tracks, 1.0 / float(spec["rate_hz"]),
                                    timing["t_start"], timing["t_measure"], timing["t_end"],
                                    pending, lock)
        cpu_s = time.process_time() - cpu0
        # the last scans' answers: wait up to the answer timeout
        deadline = time.monotonic() + float(spec["answer_timeout_s"])
        while time.monotonic() < deadline:
            with lock:
                if not pending:
                    break
            time.sleep(0.02)
        with lock:
            late = {k: v for k, v in answered.items() if v > spec["answer_timeout_s"]}
            result = {
                "robots": len(robots),
                "sent": sum(sent.values()),
                "answered": len(answered),
                "unanswered": len(pending),
                "answered_late": len(late),
                "latencies_ms": [round(v * 1e3, 3) for v in answered.values()],
                # the slowest answers, each with when its scan was sent (s into the window):
                # a server's slow moments line up across robots
                "slowest": [[round((k[1] - measure_ns) * 1e-9, 3), round(v * 1e3, 1)]
                            for k, v in sorted(answered.items(), key=lambda kv: -kv[1])[:2000]],
                "commands": counts["commands"], "unmatched_commands": counts["unmatched"],
            }
        window = timing["t_end"] - timing["t_measure"]
        rates = [n / window for n in sent.values()]
        lat = np.array(lateness) if lateness else np.zeros(1)
        result |= {
            "rate_hz_min": round(min(rates), 3), "rate_hz_mean": round(float(np.mean(rates)), 3),
            "send_lateness_p99_ms": round(float(np.percentile(lat, 99)) * 1e3, 3),
            "send_lateness_max_ms": round(float(lat.max()) * 1e3, 3),
            # over sending only (the window and the warm-up), a share of one core
            "cpu_cores": round(cpu_s / max(1e-9, timing["t_end"] - timing["t_start"]), 3),
            "bus": {"rejected": dict(bus.stats.rejected)},
        }
        return result
    finally:
        bus.close()


def main() -> None:
    def emit(obj: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(obj) + "\n")
        sys.stdout.flush()

    def timing_line() -> dict[str, Any]:
        line = sys.stdin.readline()
        if not line:
            raise SystemExit("the parent went away")
        return dict(json.loads(line))

    spec = timing_line()
    emit(run_generator(spec, timing_line, emit))


if __name__ == "__main__":
    main()
