"""Reboot benchmark: a demo whose robot reboots mid-run; prints JSON.

Runs ``mrslam demo`` (lockstep, ``--seed``) on small-house-3 and large-house-5 (``--scenario``
to pick), rebooting one robot's agent (``--robot``, default r2) once the simulation passes
``--at`` seconds (default 40): the demo kills the agent with SIGKILL and starts it again
``--down`` seconds (wall clock) later with its odometry back at zero, as a robot that lost
power (see ``DemoConfig.reboot``). Meanwhile the robot stands and the others go on.

Per run: reached, time to threshold and false merges (the report); when the agent was killed
and when it was back (the stamp of its first scan after the restart, as the demo saw it on the
bus); when the server placed the robot again: its event ``robot_joined`` "placed again in its
map by scan N since it came back" (``server.core``: the first scan after the robot's
liveliness came back that a scan match placed, not odometry alone), giving the scans and the
simulated seconds from the robot's return to its placement; and the robot's position error
against the ground truth (the server's online poses, in the robot's own map frame anchored
at its first true pose, as ``report.json`` scores them): where it was placed, the largest
after the reboot, and the last one. ``goal_met`` checks the issue's goals:

- the rebooted robot is placed again within 10 s of scans of its return;
- its final position error is at most 0.15 m (every scenario run);

and, beside them, that every run still reaches its threshold without a false merge. With
``--baseline`` each scenario also runs uninterrupted (same seed), for the same robot's errors
without a reboot.

    python bench/reboot.py [--scenario small-house-3 ...] [--robot r2] [--at 40] [--down 3]
                           [--seed 0] [--baseline] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

# run as a script, this folder comes first on sys.path and bench/sim.py would hide the
# simulator package: look in the repository instead
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

GOALS = {"placed_within_s": 10.0, "final_error_m": 0.15}
SCENARIOS = ("small-house-3", "large-house-5")
#: wall-clock bound on one demo run [s]
RUN_TIMEOUT_S = 1800.0
PLACED = re.compile(r"placed again in its map by scan (\d+)")


def demo(run: Path, scenario: str, robot: str, at_s: float | None, down_s: float,
         seed: int) -> dict[str, Any]:
    """One demo into ``run`` with ``robot`` rebooted at ``at_s`` (None: not); its report (or
    why not)."""
    from mrslam.demo import run as run_demo

    t0 = time.monotonic()
    reboot = {} if at_s is None else {"reboot": {robot: at_s}, "reboot_s": down_s}
    try:
        report = run_demo({"scenario": scenario, "seed": seed, "out": str(run), **reboot,
                           "wall_timeout_s": RUN_TIMEOUT_S}, progress=False)
    except Exception as e:   # a run that breaks is a result too
        return {"error": f"{type(e).__name__}: {e}", "wall_s": round(time.monotonic() - t0, 1)}
    return {"report": report, "wall_s": round(time.monotonic() - t0, 1)}


def position_errors(run: Path, rid: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Stamps [ns] and position errors [m] of the server's online poses of ``rid``."""
    from mrslam.run_files import Gaps, read_trajectory, read_truth
    from server.offline.scoring import anchor_transform, match_truth, pose_errors

    gaps = Gaps(run)
    truth = read_truth(run / "sim" / "truth.jsonl", gaps).get(rid)
    stamps, online = read_trajectory(run / "server" / "trajectories" / f"{rid}_online.csv", gaps)
    if truth is None or not len(stamps):
        return None
    idx, first = match_truth(stamps[:1], truth["stamps_ns"], truth["poses"])
    if not len(idx):
        return None
    T_world_own = anchor_transform(first[0], online[0])
    err = pose_errors(stamps, online, T_world_own, truth["stamps_ns"], truth["poses"])
    return err.stamps_ns, err.position_m


def score(run: Path, scenario: str, rid: str, seen: dict[str, Any]) -> dict[str, Any]:
    row: dict[str, Any] = {"scenario": scenario, "robot": rid, "out": str(run),
                           "wall_s": seen["wall_s"]}
    report = seen.get("report")
    if report is None:
        return {**row, "error": seen.get("error")}
    row.update(reached=report["reached"], sim_time_to_threshold_s=report[
        "sim_time_to_threshold_s"], false_merges=report["false_merges"], end=report["end"],
        missing=report.get("missing", []))
    reboots = report.get("agent_reboots", [])
    errors = position_errors(run, rid)
    if not reboots:
        if errors is not None:
            row["final_error_m"] = round(float(errors[1][-1]), 4)
            row["max_error_m"] = round(float(errors[1].max()), 4)
        return {**row, "rebooted": False}
    rb = reboots[0]
    row["reboot"] = {k: rb.get(k) for k in ("at_s", "killed_sim_s", "restarted_sim_s",
                                             "back_sim_s", "back_seq", "back_odom")}
    back_s = rb.get("back_sim_s")
    row["rebooted"] = back_s is not None
    placed = next((e for e in report.get("events", [])
                   if e["kind"] == "robot_joined" and rid in e["robot_ids"]
                   and PLACED.search(e["message"]) and back_s is not None
                   and e["stamp_ns"] * 1e-9 >= back_s - 1e-6), None)
    row["placed"] = placed is not None
    if placed is not None:
        m = PLACED.search(placed["message"])
        assert m is not None
        row["placed_after_scans"] = int(m.group(1))
        row["placed_at_sim_s"] = round(placed["stamp_ns"] * 1e-9, 3)
        row["placed_after_sim_s"] = round(placed["stamp_ns"] * 1e-9 - back_s, 3)
    if errors is not None:
        stamps_s, err_m = errors[0] * 1e-9, errors[1]
        row["final_error_m"] = round(float(err_m[-1]), 4)
        row["final_at_sim_s"] = round(float(stamps_s[-1]), 2)
        if back_s is not None:
            before = err_m[stamps_s < rb["killed_sim_s"]]
            after = err_m[stamps_s >= back_s]
            row["max_error_before_reboot_m"] = (round(float(before.max()), 4)
                                                if len(before) else None)
            row["max_error_after_reboot_m"] = round(float(after.max()), 4) if len(after) else None
        if placed is not None:
            at = np.flatnonzero(np.abs(stamps_s - placed["stamp_ns"] * 1e-9) < 1e-6)
            row["placed_error_m"] = round(float(err_m[at[0]]), 4) if len(at) else None
    others = {r: v.get("max_position_error_m") for r, v in report.get("robots", {}).items()
              if r != rid}
    row["other_robots_max_position_error_m"] = others
    return row


def goal_met(runs: list[dict[str, Any]]) -> dict[str, bool]:
    return {
        "placed_within_10s_of_scans": bool(runs) and all(
            r.get("placed") and r["placed_after_sim_s"] <= GOALS["placed_within_s"]
            for r in runs),
        "final_error_within_0.15m": bool(runs) and all(
            r.get("final_error_m") is not None and r["final_error_m"] <= GOALS["final_error_m"]
            for r in runs),
        "every_run_reaches_threshold_without_false_merges": bool(runs) and all(
            r.get("reached") and r.get("false_merges") == 0 for r in runs),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", action="append", default=None,
                    help=f"scenario to run (repeatable; default {' and '.join(SCENARIOS)})")
    ap.add_argument("--robot", default="r2", help="the robot that reboots")
    ap.add_argument("--at", type=float, default=40.0, help="sim time of the reboot [s]")
    ap.add_argument("--down", type=float, default=3.0,
                    help="wall-clock time the agent stays down [s]")
    ap.add_argument("--seed", type=int, default=0, help="the simulator's seed")
    ap.add_argument("--baseline", action="store_true",
                    help="also run each scenario uninterrupted, for comparison")
    ap.add_argument("--out", type=Path, default=None, help="keep the run folders here")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="mrslam-reboot-"))
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for scenario in args.scenario or SCENARIOS:
        run = out / f"{scenario}-seed{args.seed}"
        seen = demo(run, scenario, args.robot, args.at, args.down, args.seed)
        runs.append(score(run, scenario, args.robot, seen))
        if args.baseline:
            base = out / f"{scenario}-seed{args.seed}-uninterrupted"
            row = score(base, scenario, args.robot,
                        demo(base, scenario, args.robot, None, args.down, args.seed))
            runs[-1]["uninterrupted"] = {k: row.get(k) for k in (
                "reached", "sim_time_to_threshold_s", "false_merges", "final_error_m",
                "max_error_m", "wall_s")}
    json.dump({"robot": args.robot, "at_s": args.at, "down_s": args.down, "seed": args.seed,
               "out": str(out), "goals": GOALS, "runs": runs, "goal_met": goal_met(runs)},
              sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
