"""Exploration benchmark: the dissertation's single-robot cases with both explorers; prints JSON.

Each run is a full `mrslam demo` (server, simulator, agent as processes on loopback, lockstep).

    python bench/explore.py [--cases thesis-case-1 thesis-case-3] [--explorers voronoi frontier]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

# run as a script, this folder comes first on sys.path and bench/sim.py would hide the
# simulator package: look in the repository instead
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))
#: the dissertation's worlds and cases (the package ships its own worlds; these benchmarks
#: measure the dissertation's)
THESIS_SCENARIOS = _HERE.parent.parent / "shared" / "data" / "worlds" / "thesis" / "scenarios.yaml"

GOALS = {"thesis-case-1": {"max_position_error_m": 0.10},
         "thesis-case-3": {"max_position_error_m": 0.30}}


def one(case: str, explorer: str, seed: int, out: Path, max_sim_time_s: float) -> dict[str, Any]:
    from mrslam.demo import run

    r = run({"scenario": case, "scenarios_file": str(THESIS_SCENARIOS), "explorer": explorer,
             "seed": seed, "out": str(out),
             "max_sim_time_s": max_sim_time_s, "wall_timeout_s": 3600}, progress=False)
    robots = r["robots"]
    return {
        "reached": r["reached"], "threshold": r["threshold"], "area_m2": r["area_m2"],
        "sim_time_to_threshold_s": r["sim_time_to_threshold_s"],
        "final_coverage": max((t["coverage"] or 0.0) for t in r["teams"].values()),
        "true_coverage": r["true_coverage"], "phantom_area_m2": r["phantom_area_m2"],
        "max_position_error_m": max(x["max_position_error_m"] or 0.0 for x in robots.values()),
        "max_yaw_error_rad": max(x["max_yaw_error_rad"] or 0.0 for x in robots.values()),
        "ate_rmse_m": max(x["ate_rmse_m"] or 0.0 for x in robots.values()),
        "collisions": sum(x["collisions"] for x in robots.values()),
        "distance_m": sum(x["distance_m"] for x in robots.values()),
        "decision_ms_median": [x["decision_ms_median"] for x in robots.values()],
        "wall_time_s": r["wall_time_s"], "end": r["end"], "run": str(out),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", nargs="+", default=["thesis-case-1", "thesis-case-3"])
    ap.add_argument("--explorers", nargs="+", default=["voronoi", "frontier"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-sim-time", type=float, default=7200.0)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    base = a.out or Path(tempfile.mkdtemp(prefix="mrslam-explore-"))
    results: dict[str, Any] = {}
    for case in a.cases:
        results[case] = {}
        for explorer in a.explorers:
            print(f"running {case} with {explorer}...", file=sys.stderr)
            results[case][explorer] = one(case, explorer, a.seed, base / f"{case}-{explorer}",
                                          a.max_sim_time)
        times = {e: results[case][e]["sim_time_to_threshold_s"] for e in a.explorers}
        if "voronoi" in times and "frontier" in times:
            v, f = times["voronoi"], times["frontier"]
            results[case]["voronoi_faster"] = (v is not None and (f is None or v < f))
        results[case]["goals"] = GOALS.get(case, {})
    print(json.dumps({"bench": "explore", "seed": a.seed, "results": results}, indent=2))


if __name__ == "__main__":
    main()
