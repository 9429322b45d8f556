"""The server's CPU per scan, in process and stage by stage: where a scan's milliseconds go.

``bench/load.py`` measures the whole server over Zenoh; this feeds the same recorded tracks
(``bench.support.load_gen``: robots wandering the large house, 10 Hz, each its own team, as in
the load bench) straight into one ``ServerCore``, robot after robot, step after step, with no
bus and no other process (replanning in line, as in lockstep). It prints, as JSON:

- ``cpu_ms_per_scan``: the process's CPU time over the scans of the measuring window;
- ``stages_ms_per_scan``: the same time by stage, from a profile of the window (each stage's
  functions, cumulative; a function in two stages counts once, in the first);
- ``top``: the functions with the most time of their own.

    python bench/scan_cost.py [--robots 10] [--steps 300] [--warmup 100] [--no-profile]
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import pstats
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: stage -> qualified names (file fragment, function) whose cumulative time it is
STAGES: dict[str, list[tuple[str, str]]] = {
    "scan to points and normals": [("slam/scan.py", "prepare"), ("slam/scan.py", "line_normals"),
                                   ("slam/sensor.py", "prepare")],
    "matching (ICP, correlative)": [("slam/frontend.py", "match_scan"),
                                    ("slam/icp.py", "icp")],
    "keyframes, graph, loop closure": [("slam/robot.py", "_add_keyframe"),
                                       ("slam/robot.py", "_close_loops")],
    "grid updates": [("slam/mapping.py", "update"), ("slam/mapping.py", "update_many")],
    "steering (pursuit, VFH, lookout)": [("command/steering.py", "command")],
    "decisions and replans": [("exploration/navigator.py", "_decide"),
                              ("exploration/navigator.py", "_replan_to_target")],
    "coverage and maps": [("fleet/progress.py", "tick"), ("core.py", "map_updates")],
    "decoding": [("schemas/codec.py", "decode"), ("schemas/messages.py", "ranges_m")],
}


def run(robots: int, steps: int, warmup: int, profile: bool) -> dict[str, Any]:
    import numpy as np

    from bench.support.load_gen import make_tracks, pingpong
    from schemas import Scan, decode, encode
    from server.config import ServerConfig
    from server.core import ServerCore

    tracks = make_tracks(max(steps // 2, 100))
    cfg = ServerConfig.model_validate({"robots": None})
    core = ServerCore(cfg)
    n_tracks = tracks.ranges_mm.shape[0]
    wire: list[list[bytes]] = []
    for i in range(robots):
        rid = f"r{i + 1}"
        track, offset = i % n_tracks, (i * 37) % tracks.steps
        frames = []
        for k in range(warmup + steps):
            j = pingpong(k + offset, tracks.steps)
            frames.append(encode(Scan(
                robot_id=rid, seq=k, stamp_ns=(k + 1) * 100_000_000,
                odom_pose=tuple(float(v) for v in tracks.odom[track, j]),
                angle_min_rad=tracks.angle_min_rad,
                angle_increment_rad=tracks.angle_increment_rad,
                range_min_mm=tracks.range_min_mm, range_max_mm=tracks.range_max_mm,
                ranges_mm=tracks.ranges_mm[track, j].tobytes())))
        wire.append(frames)

    commands = hashlib.sha1()

    def step(k: int) -> None:
        for i in range(robots):
            scan = decode(wire[i][k], Scan)
            commands.update(encode(core.on_scan(scan, scan.stamp_ns)))

    for k in range(warmup):
        step(k)
    prof = cProfile.Profile() if profile else None
    t0, w0 = time.process_time(), time.perf_counter()
    per_step = []
    if prof is not None:
        prof.enable()
    for k in range(warmup, warmup + steps):
        c0 = time.process_time()
        step(k)
        per_step.append((time.process_time() - c0) / robots * 1e3)
    if prof is not None:
        prof.disable()
    cpu = time.process_time() - t0
    out: dict[str, Any] = {
        "robots": robots, "steps": steps, "scans": robots * steps,
        "cpu_ms_per_scan": round(cpu / (robots * steps) * 1e3, 3),
        "cpu_ms_per_scan_median_step": round(float(np.median(per_step)), 3),
        "cpu_ms_per_scan_p90_step": round(float(np.percentile(per_step, 90)), 3),
        "wall_s": round(time.perf_counter() - w0, 2), "profiled": profile,
        "keyframes": {rid: r.slam.stats.keyframes for rid, r in core.robots.items()},
        # the same behaviour before and after a change that should not change it: the same
        # commands, bit for bit
        "commands_sha1": commands.hexdigest(),
    }
    if prof is not None:
        out |= _stages(pstats.Stats(prof), robots * steps)
    return out


def _ours(file: str) -> bool:
    """Whether a profiled function is this project's code (not a library's)."""
    return file.startswith(str(ROOT)) and ".venv" not in file


def _stages(stats: pstats.Stats, scans: int) -> dict[str, Any]:
    raw: dict[Any, Any] = stats.stats  # type: ignore[attr-defined]
    cumulative: dict[tuple[str, str], float] = {}
    own: list[tuple[float, str, int]] = []
    for (file, _line, name), (_cc, nc, tt, ct, _callers) in raw.items():
        cumulative[(file, name)] = cumulative.get((file, name), 0.0) + ct
        own.append((tt, f"{Path(file).parent.name}/{Path(file).name}:{name}", nc))
    stages = {}
    for stage, names in STAGES.items():
        t = sum(ct for (file, name), ct in cumulative.items()
                if any(file.endswith(f) and name == n for f, n in names))
        stages[stage] = round(t / scans * 1e3, 3)
    own.sort(reverse=True)
    top = [{"function": name, "own_ms_per_scan": round(tt / scans * 1e3, 3), "calls": nc}
           for tt, name, nc in own[:25]]
    ours = sorted(((ct, f"{Path(f).parent.name}/{Path(f).name}:{n}")
                   for (f, n), ct in cumulative.items() if _ours(f)), reverse=True)
    cum = [{"function": name, "cumulative_ms_per_scan": round(ct / scans * 1e3, 3)}
           for ct, name in ours[:40]]
    return {"stages_ms_per_scan": stages, "top": top, "cumulative": cum}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--steps", type=int, default=300, help="measured steps (10 Hz each)")
    ap.add_argument("--warmup", type=int, default=100, help="steps before measuring")
    ap.add_argument("--no-profile", action="store_true",
                    help="no profile: the CPU time without the profiler's own cost")
    args = ap.parse_args()
    print(json.dumps(run(args.robots, args.steps, args.warmup, not args.no_profile), indent=2))


if __name__ == "__main__":
    main()
