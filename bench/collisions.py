"""Robots close together: do they drive into each other? Prints JSON.

Spawns robots in pairs a short distance apart (default: beside each of the five start poses of
the large house, 1 m apart, ten robots) and runs the demo in lockstep for ``--max-sim-time``
seconds (the start, when the pairs are still close, is what matters; ``--full`` runs to the
coverage threshold). The simulator counts every contact of a robot's body with a wall, an
obstacle or another robot's body; the report's per-robot ``collisions`` are summed here.
Pairs stand side by side (the second robot ``--gap`` metres to the left of the first, facing
the same way), so both must turn or drive past each other to leave.

    python bench/collisions.py [--gap 1.0] [--max-sim-time 120] [--full] [--seed 0]
                               [--rtf 5] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

#: the large house's five start poses (the package's scenario large-house-5)
STARTS = [(-23.0, -22.0, 0.0), (22.0, -22.0, math.pi), (22.0, 17.0, math.pi),
          (-5.0, 20.0, 0.0), (-21.0, 22.0, 0.0)]
GOALS = {"collisions": 0}


def spawns(gap_m: float) -> dict[str, tuple[float, float, float]]:
    """Two robots per start pose: the first on it, the second ``gap_m`` to its left."""
    out: dict[str, tuple[float, float, float]] = {}
    for i, (x, y, yaw) in enumerate(STARTS):
        out[f"r{i + 1}"] = (x, y, yaw)
        out[f"r{i + 1 + len(STARTS)}"] = (x - gap_m * math.sin(yaw), y + gap_m * math.cos(yaw),
                                          yaw)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gap", type=float, default=1.0, help="distance between a pair [m]")
    ap.add_argument("--max-sim-time", type=float, default=120.0, help="sim time per run [s]")
    ap.add_argument("--full", action="store_true", help="run to the coverage threshold")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rtf", type=float, default=None,
                    help="real time × RTF instead of lockstep: the server must keep up (at "
                    "RTF 5 ten robots send fifty robots' worth of scans)")
    ap.add_argument("--out", type=Path, default=None, help="keep the run folder here")
    args = ap.parse_args()
    from mrslam.demo import run

    out = args.out or Path(tempfile.mkdtemp(prefix="mrslam-collisions-"))
    robots = spawns(args.gap)
    report = run({"scenario": "large-house-5", "robots": {k: list(v) for k, v in robots.items()},
                  "seed": args.seed, "out": str(out),
                  "max_sim_time_s": 3600.0 if args.full else args.max_sim_time,
                  "record": False, "wall_timeout_s": 5400,
                  **({"lockstep": False, "rtf": args.rtf} if args.rtf else {})},
                 progress=False)
    per_robot: dict[str, Any] = {rid: r["collisions"] for rid, r in report["robots"].items()}
    total = sum(per_robot.values())
    json.dump({"robots": len(robots), "gap_m": args.gap, "seed": args.seed,
               "mode": f"real time x{args.rtf}" if args.rtf else "lockstep",
               "sim_time_s": report["sim_time_s"], "reached": report["reached"],
               "collisions": total, "collisions_per_robot": per_robot,
               "false_merges": report["false_merges"], "out": str(out),
               "goal_met": {"no_collisions": total == GOALS["collisions"]}},
              sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
