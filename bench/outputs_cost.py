"""What rewriting a long mission's outputs costs, and what of it holds the worker; prints JSON.

A mission of ``--robots`` robots, ``--hours`` long, at 10 scans a second and a keyframe every
``--scans-per-keyframe`` scans (each with ``--beams`` returns, spilled to the render store as
the server does), is made up of synthetic scans. Measured, in CPU seconds of the thread doing
it:

- ``cloud_s``: the teams' point clouds (every keyframe's returns, thinned to 5 cm), which the
  worker made at every round before and the writer thread makes now;
- ``trajectories_s``: the CSV and TUM files of every robot's online and final trajectories
  (the writer thread);
- ``interval_s``: when ``OutputPacer`` puts the next round after one that cost that much
  (``outputs_period_s`` 10 s).

    python bench/outputs_cost.py [--robots 10] [--hours 1.0] [--beams 360]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--beams", type=int, default=360)
    ap.add_argument("--scans-per-keyframe", type=float, default=3.0)
    args = ap.parse_args()

    import numpy as np

    from server.runtime.outputs import OutputPacer, write_trajectory, write_tum
    from server.slam.keyframes import Keyframe
    from server.slam.mapping import point_cloud
    from server.slam.scan import scan_to_points

    rng = np.random.default_rng(0)
    scans = int(args.hours * 3600 * 10)
    keyframes = int(scans / args.scans_per_keyframe)
    angles = np.linspace(-np.pi, np.pi, args.beams, endpoint=False)
    # one robot's keyframes, along a wandering path through rooms of a few metres
    kfs, poses = [], np.zeros((keyframes, 3))
    xy, th = np.zeros(2), 0.0
    for k in range(keyframes):
        th += rng.normal(0, 0.2)
        xy = xy + 0.3 * np.array([np.cos(th), np.sin(th)])
        poses[k] = (xy[0], xy[1], th)
        ranges = rng.uniform(1.0, 8.0) * (1 + 0.2 * np.sin(3 * angles + k))
        kfs.append(Keyframe.create(k, k, scan_to_points(ranges, angles, 0.05, 40.0),
                                   poses[k].copy()))
    t0 = time.thread_time()
    cloud = point_cloud(kfs, poses)
    cloud_s = (time.thread_time() - t0) * args.robots
    stamps = np.arange(scans, dtype=np.int64) * 100_000_000 + 1_700_000_000_000_000_000
    traj = rng.normal(size=(scans, 3))
    with tempfile.TemporaryDirectory() as d:
        t0 = time.thread_time()
        write_trajectory(Path(d) / "a.csv", stamps, traj)
        write_tum(Path(d) / "a.tum", stamps, traj)
        trajectories_s = (time.thread_time() - t0) * 2 * args.robots   # online and final
    pacer = OutputPacer(10.0)
    pacer.write_cpu_s = cloud_s + trajectories_s
    print(json.dumps({
        "robots": args.robots, "hours": args.hours, "scans_per_robot": scans,
        "keyframes_per_robot": keyframes, "cloud_points_per_robot": len(cloud),
        "cloud_s": round(cloud_s, 3), "trajectories_s": round(trajectories_s, 3),
        "round_s": round(cloud_s + trajectories_s, 3),
        "interval_s": round(pacer.next_in(), 1),
        "share_of_a_core_at_10_s": round((cloud_s + trajectories_s) / 10.0, 3),
    }))


if __name__ == "__main__":
    main()
