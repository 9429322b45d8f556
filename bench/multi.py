"""Multi-robot benchmark: the dissertation's four cases as full demo runs; prints JSON.

Cases 1 and 3 are single robots, 2 and 4 teams (3 and 5 robots) that merge at rendezvous.
Reports each case's time to threshold, the team speed-ups (case 1 / case 2, case 3 / case 4),
merge transform errors after joint optimisation against the direct method on the same
sightings, and — with ``--spurious`` — the team cases again with that share of false tag views.

    python bench/multi.py [--cases 1 2 3 4] [--spurious 0.2] [--known-starts] [--thesis-rule]
                          [--runs N] [--out DIR]

Runs with several robots are not exactly repeatable (the server's timing feeds back into the
simulation), so ``--runs N`` runs each team case N times and adds every run's speed-up and
their median; merge figures then cover all runs.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

# run as a script, this folder comes first on sys.path and bench/sim.py would hide the
# simulator package: look in the repository instead
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))
#: the dissertation's worlds and cases (the package ships its own worlds; these benchmarks
#: measure the dissertation's)
THESIS_SCENARIOS = _HERE.parent.parent / "shared" / "data" / "worlds" / "thesis" / "scenarios.yaml"

GOALS = {"speedup_case2": 2.5, "speedup_case4": 3.5, "merge_error_m": 0.05,
         "merge_error_deg": 1.0, "max_position_error_m": {"2": 0.15, "4": 0.40}}


def one(case: str, out: Path, seed: int, spurious: float, max_sim_time_s: float,
        known_starts: bool = False, coordination: str = "optimal") -> dict[str, Any]:
    from mrslam.demo import run

    r = run({"scenario": f"thesis-case-{case}", "scenarios_file": str(THESIS_SCENARIOS),
             "seed": seed, "out": str(out),
             "spurious_detections": spurious, "max_sim_time_s": max_sim_time_s,
             "known_starts": known_starts, "coordination": coordination,
             "wall_timeout_s": 5400}, progress=False)
    robots = r["robots"]
    merges = r.get("merges", [])
    return {
        "reached": r["reached"], "threshold": r["threshold"],
        "sim_time_to_threshold_s": r["sim_time_to_threshold_s"],
        "first_team_time_to_threshold_s": r.get("first_team_time_to_threshold_s"),
        "teams": {k: {"robots": v["robot_ids"], "coverage": v.get("coverage"),
                      "merged_into": v.get("merged_into"),
                      "sim_time_to_threshold_s": v.get("sim_time_to_threshold_s")}
                  for k, v in r["teams"].items()},
        "true_coverage": r["true_coverage"], "phantom_area_m2": r["phantom_area_m2"],
        "max_position_error_m": max(x["max_position_error_m"] or 0.0 for x in robots.values()),
        "max_yaw_error_rad": max(x["max_yaw_error_rad"] or 0.0 for x in robots.values()),
        "collisions": sum(x["collisions"] for x in robots.values()),
        "merges": merges, "false_merges": r.get("false_merges", 0),
        "tag_counters": r.get("tag_counters", {}),
        "wall_time_s": r["wall_time_s"], "end": r["end"], "run": str(out),
    }


def ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a and b else None


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", nargs="+", default=["1", "2", "3", "4"])
    ap.add_argument("--spurious", type=float, default=0.2,
                    help="also run the team cases with this share of false views (0: skip)")
    ap.add_argument("--known-starts", action="store_true",
                    help="also run the team cases with the start poses given to the server "
                    "(one team from the start: what coordination alone gains)")
    ap.add_argument("--thesis-rule", action="store_true",
                    help="also run the team cases with the dissertation's target rule "
                    "(--coordination thesis) instead of the optimal assignment")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=1,
                    help="run each team case (2, 4) this many times (single robots repeat "
                    "exactly and run once)")
    ap.add_argument("--max-sim-time", type=float, default=7200.0)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    base = a.out or Path(tempfile.mkdtemp(prefix="mrslam-multi-"))
    res: dict[str, Any] = {"cases": {}, "goals": GOALS}
    for case in a.cases:
        print(f"running case {case}...", file=sys.stderr)
        res["cases"][case] = one(case, base / f"case-{case}", a.seed, 0.0, a.max_sim_time)
        for k in range(2, a.runs + 1 if case in ("2", "4") else 1):
            print(f"running case {case} again ({k} of {a.runs})...", file=sys.stderr)
            res["cases"][f"{case}#{k}"] = one(case, base / f"case-{case}-run{k}", a.seed, 0.0,
                                              a.max_sim_time)
        if a.spurious > 0 and case in ("2", "4"):
            print(f"running case {case} with {a.spurious:.0%} false views...", file=sys.stderr)
            res["cases"][f"{case}-spurious"] = one(case, base / f"case-{case}-spurious",
                                                   a.seed, a.spurious, a.max_sim_time)
        if a.known_starts and case in ("2", "4"):
            print(f"running case {case} with known start poses...", file=sys.stderr)
            res["cases"][f"{case}-known-starts"] = one(case, base / f"case-{case}-known-starts",
                                                       a.seed, 0.0, a.max_sim_time, True)
        if a.thesis_rule and case in ("2", "4"):
            print(f"running case {case} with the dissertation's target rule...", file=sys.stderr)
            res["cases"][f"{case}-thesis-rule"] = one(case, base / f"case-{case}-thesis-rule",
                                                      a.seed, 0.0, a.max_sim_time,
                                                      coordination="thesis")
    c = res["cases"]

    def t(k: str) -> float | None:
        return c[k]["sim_time_to_threshold_s"] if k in c else None

    def first(k: str) -> float | None:
        return c[k]["first_team_time_to_threshold_s"] if k in c else None

    # all final teams at the threshold (the goal's measure), and the first team alone
    res["speedup_case2"] = ratio(t("1"), t("2"))
    res["speedup_case4"] = ratio(t("3"), t("4"))
    res["speedup_case2_first_team"] = ratio(t("1"), first("2"))
    res["speedup_case4_first_team"] = ratio(t("3"), first("4"))
    for k, single in (("2", "1"), ("4", "3")):
        runs = [ratio(t(single), t(key)) for key in c if key.split("#")[0] == k]
        if len(runs) > 1 and None not in runs:
            res[f"speedup_case{k}_runs"] = runs
            res[f"speedup_case{k}_median"] = float(np.median(np.asarray(runs, dtype=float)))
    for k in ("2", "4"):
        if f"{k}-known-starts" in c:
            res[f"speedup_case{k}_known_starts"] = ratio(t(str(int(k) - 1)),
                                                         t(f"{k}-known-starts"))
        if f"{k}-thesis-rule" in c:
            res[f"speedup_case{k}_thesis_rule"] = ratio(t(str(int(k) - 1)),
                                                        t(f"{k}-thesis-rule"))
    merges = [m for k in c if k.split("#")[0] in ("2", "4") for m in c[k]["merges"]
              if "joint_error_m" in m and m.get("kind", "tags") == "tags"]
    if merges:
        res["merge_error_joint_max_m"] = max(m["joint_error_m"] for m in merges)
        res["merge_error_joint_max_deg"] = max(m["joint_error_deg"] for m in merges)
        res["merge_error_direct_max_m"] = max(m["direct_error_m"] for m in merges)
        res["merge_error_direct_max_deg"] = max(m["direct_error_deg"] for m in merges)
        meet = [m for m in merges if "meeting_error_m" in m]
        if meet:
            res["merge_error_meeting_max_m"] = max(m["meeting_error_m"] for m in meet)
            res["merge_error_meeting_max_deg"] = max(m["meeting_error_deg"] for m in meet)
        res["joint_better_than_direct"] = sum(
            m["joint_error_m"] <= m["direct_error_m"] for m in merges) / len(merges)
        fin = [m for m in merges if "final_error_m" in m]
        if fin:  # the start-frame transform as the final joint map has it
            res["merge_error_final_max_m"] = max(m["final_error_m"] for m in fin)
            res["merge_error_final_max_deg"] = max(m["final_error_deg"] for m in fin)
            res["final_better_than_direct"] = sum(
                m["final_error_m"] <= m["direct_error_m"] for m in fin) / len(fin)
    res["false_merges"] = {k: v["false_merges"] for k, v in c.items()}
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
