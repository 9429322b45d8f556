"""Simulator speed; prints JSON.

- raycast: 400-beam scans per second in the large thesis world on one core, from random free
  poses (the goal is >= 2,000).
- core: simulator steps per second (5 robots: physics, 5 scans, camera checks) without the bus.
- lockstep: ``mrslam sim --lockstep`` with the five robots of thesis-case-4 at 10 Hz and one
  ``mrslam agent`` process per robot (no server, so the agents ack at once), all over a real
  Zenoh router on loopback; the real-time factor is simulated time over the wall time of
  stepping (the goal is >= 20).

    python bench/sim.py [--scans N] [--sim-s S] [--skip-lockstep]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# Run as ``python bench/sim.py``, this file's folder comes first on sys.path and its name would
# hide the ``sim`` package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "bench"]
sys.path.insert(0, str(ROOT))
THESIS = ROOT.parent / "shared" / "data" / "worlds" / "thesis"


def free_poses(n: int, seed: int = 0) -> list[tuple[float, float, float]]:
    from sim.loader import load_world
    from sim.robot import collisions, point_in_polygons

    world = load_world(THESIS / "house_large.world")
    xmin, ymin, xmax, ymax = world.bounds()
    rng = np.random.default_rng(seed)
    out: list[tuple[float, float, float]] = []
    while len(out) < n:
        p = rng.uniform([xmin, ymin, -math.pi], [xmax, ymax, math.pi], (4 * n, 3))
        ok = ~collisions(p[:, :2], 0.13, world.segments, world.circles)
        ok &= ~point_in_polygons(p[:, :2], world.polygons)
        out += [tuple(map(float, q)) for q in p[ok]]
    return out[:n]


def bench_raycast(n_scans: int) -> dict[str, object]:
    from sim.loader import load_world
    from sim.raycast import RayCaster

    world = load_world(THESIS / "house_large.world")
    caster = RayCaster(world.segments, world.circles)
    poses = free_poses(n_scans)
    others = np.array([[0.0, 0.0, 0.13], [5.0, 5.0, 0.13], [-10.0, 3.0, 0.13], [7.0, -8.0, 0.13]])
    inc = 2 * math.pi / 400
    for p in poses[:50]:  # warm-up
        caster.cast(p, 400, -math.pi, inc, 10.0, others)
    t0 = time.perf_counter()
    hits = 0
    for p in poses:
        hits += int(np.isfinite(caster.cast(p, 400, -math.pi, inc, 10.0, others)).sum())
    dt = time.perf_counter() - t0
    return {"scans": n_scans, "beams": 400, "segments": len(world.segments),
            "seconds": round(dt, 3), "scans_per_s": round(n_scans / dt, 1),
            "mean_hits_per_scan": round(hits / n_scans, 1), "goal_scans_per_s": 2000}


def bench_core(steps: int) -> dict[str, object]:
    from sim.config import SimConfig
    from sim.process import build

    sim, _ = build(SimConfig(scenario="thesis-case-4",
                             scenarios_file=str(THESIS / "scenarios.yaml")))
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for _ in range(steps):
        for rid in sim.robots:
            sim.set_command(rid, 0.3, float(rng.uniform(-0.5, 0.5)))
        sim.sense()
        sim.advance()
    dt = time.perf_counter() - t0
    return {"robots": len(sim.robots), "steps": steps, "steps_per_s": round(steps / dt, 1),
            "real_time_factor_without_bus": round(steps * 0.1 / dt, 1)}


def bench_lockstep(sim_s: float) -> dict[str, object]:
    from schemas.bus import free_local_endpoint

    endpoint = free_local_endpoint()
    exe = [sys.executable, "-m", "mrslam.cli"]
    env = dict(os.environ, PYTHONPATH=str(ROOT),
               MRSLAM_SCENARIOS_FILE=str(THESIS / "scenarios.yaml"))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        sim = subprocess.Popen([*exe, "sim", "--scenario", "thesis-case-4", "--lockstep",
                                "--listen", endpoint, "--duration", str(sim_s), "--out",
                                str(out)], cwd=ROOT, env=env)
        time.sleep(1.0)
        agents = [subprocess.Popen([*exe, "agent", "--robot-id", f"r{i}", "--connect",
                                    endpoint], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)
                  for i in range(1, 6)]
        try:
            sim.wait(timeout=600)
        finally:
            for a in agents:
                a.terminate()
            for a in agents:
                a.wait(timeout=30)
        summary = json.loads((out / "summary.json").read_text())
    return {"robots": 5, "rate_hz": 10, "sim_time_s": summary["sim_time_s"],
            "stepping_wall_s": round(summary["stepping_wall_s"], 3),
            "real_time_factor": round(summary["real_time_factor"], 1),
            "ack_timeouts": summary["ack_timeouts"], "resends": summary["resends"],
            "goal_real_time_factor": 20}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=4000)
    ap.add_argument("--core-steps", type=int, default=300)
    ap.add_argument("--sim-s", type=float, default=100.0)
    ap.add_argument("--skip-lockstep", action="store_true")
    args = ap.parse_args()
    report: dict[str, object] = {"raycast": bench_raycast(args.scans),
                                 "core": bench_core(args.core_steps)}
    if not args.skip_lockstep:
        report["lockstep"] = bench_lockstep(args.sim_s)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
