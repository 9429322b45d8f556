"""Recovery benchmark: the default demo with its server SIGKILLed mid-run; prints JSON.

Runs ``mrslam demo --seed 0`` once uninterrupted, then ``--kills K`` times (default 5) killing
the server once with SIGKILL at a simulated time drawn uniformly from ``--window`` (20-80 s;
seeded by ``--rng-seed``), watched on the bus's simulator clock. The demo restarts the server,
which resumes from its journal. Per run: reached, time to threshold, false merges, the team
coverage just before the kill and just after the restart (from the report's coverage history;
as the bus showed it too), the final true robot poses against the uninterrupted run's, and the
recovery time: restart to the server's first velocity command on the bus (the demo's monitor
measures it), beside the whole outage as this program's own client saw it (kill to first
command), and how much simulated time passed meanwhile with the robots standing (in lockstep
the simulator does not wait for agents it cannot reach). ``goal_met`` checks the issue's goals:

- every run reaches 98 % with no false merge;
- the team coverage after each restart is at least 99 % of what it was before (nothing lost);
- the final poses are within 2 cm of the uninterrupted run's;
- recovery within 5 s;
- the journal and snapshots write ≤ 50 KB per robot per second of scans and take ≤ 5 % of
  the server's CPU (the uninterrupted run's server summary).

    python bench/recovery.py [--kills K] [--window 20 80] [--rng-seed 0] [--out DIR]
                             [--scenario NAME]
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
from typing import Any

import numpy as np
import yaml

# run as a script, this folder comes first on sys.path and bench/sim.py would hide the
# simulator package: look in the repository instead
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

GOALS = {"threshold": 0.98, "coverage_kept": 0.99, "final_pose_m": 0.02, "recovery_s": 5.0,
         "kb_per_robot_s": 50.0, "cpu_fraction": 0.05}
#: wall-clock bound on one demo run [s]
RUN_TIMEOUT_S = 1800.0


class BusWatch:
    """A client on the demo's bus: the simulator's clock and when commands go to robots."""

    def __init__(self, endpoint: str) -> None:
        from schemas import SimClock, keys
        from schemas.bus import Bus

        self.sim_time_s = 0.0
        self.commands_at: list[float] = []   # time.monotonic() of every command seen
        self._lock = threading.Lock()
        self.bus = Bus.open("client", connect=[endpoint], connect_timeout_ms=10000)
        self.bus.subscribe(keys.SIM_CLOCK, SimClock, self._on_clock)
        self.bus.subscribe_raw(f"{keys.ROOT}/robot/*/cmd_vel", self._on_command)

    def _on_clock(self, key: str, msg: Any) -> None:
        self.sim_time_s = msg.stamp_ns * 1e-9

    def _on_command(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.commands_at.append(time.monotonic())

    def first_command_after(self, t: float) -> float | None:
        with self._lock:
            return next((c for c in self.commands_at if c > t), None)

    def close(self) -> None:
        self.bus.close()


def server_pids(run: Path) -> list[int]:
    """Processes running ``mrslam server -c <run>/server.yaml``."""
    found = subprocess.run(["pgrep", "-f", f"mrslam server -c {run / 'server.yaml'}"],
                           capture_output=True, text=True, check=False)
    return [int(p) for p in found.stdout.split()]


def connect(run: Path, demo: subprocess.Popen[bytes]) -> BusWatch | None:
    """A BusWatch on the demo's bus once its server is up; None if the demo ended first."""
    from schemas.bus import BusError

    while demo.poll() is None:
        try:
            endpoint = yaml.safe_load((run / "server.yaml").read_text())["bus"]["listen"][0]
            return BusWatch(endpoint)
        except (OSError, TypeError, KeyError, BusError):   # not written or not up yet
            time.sleep(0.5)
    return None


def demo(run: Path, kill_at_s: float | None, scenario: str | None = None) -> dict[str, Any]:
    """One ``mrslam demo --seed 0`` into ``run`` (the default scenario, or ``scenario``); with
    ``kill_at_s``, its server SIGKILLed once the simulation passes that time. What this
    program saw of it."""
    cmd = [sys.executable, "-m", "mrslam", "demo", "--seed", "0", "--out", str(run),
           *(["--scenario", scenario] if scenario else [])]
    seen: dict[str, Any] = {"kill_at_s": kill_at_s}
    t0 = time.monotonic()
    with (run.parent / f"{run.name}.log").open("wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        try:
            if kill_at_s is not None:
                seen.update(kill(run, proc, kill_at_s))
            proc.wait(timeout=RUN_TIMEOUT_S)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    seen.update(exit_code=proc.returncode, wall_s=round(time.monotonic() - t0, 1))
    return seen


def kill(run: Path, proc: subprocess.Popen[bytes], at_s: float) -> dict[str, Any]:
    watch = connect(run, proc)
    if watch is None:
        return {"killed": False}
    try:
        while watch.sim_time_s < at_s and proc.poll() is None:
            time.sleep(0.02)
        pids = server_pids(run)
        if proc.poll() is not None or len(pids) != 1:
            return {"killed": False}
        sim_s, killed_at = watch.sim_time_s, time.monotonic()
        os.kill(pids[0], signal.SIGKILL)
        while watch.first_command_after(killed_at + 0.5) is None and proc.poll() is None \
                and time.monotonic() - killed_at < 120:
            time.sleep(0.05)
        back = watch.first_command_after(killed_at + 0.5)
        return {"killed": True, "killed_pid": pids[0], "killed_at_sim_s": round(sim_s, 2),
                "outage_s": round(back - killed_at, 3) if back is not None else None}
    finally:
        watch.close()


def coverage_at(report: dict[str, Any], sim_s: float, after: bool) -> float | None:
    """The team coverage (the best team's) in the report's history: its last entry at or
    before ``sim_s``, or (``after``) its first entry after it."""
    best: float | None = None
    for team in report.get("teams", {}).values():
        hist = team.get("coverage_history", [])
        pick = (next((c for t, c in hist if t > sim_s), None) if after
                else next((c for t, c in reversed(hist) if t <= sim_s), None))
        if pick is not None and (best is None or pick > best):
            best = pick
    return best


def final_poses(run: Path) -> dict[str, list[float]]:
    try:
        robots = json.loads((run / "sim" / "summary.json").read_text())["robots"]
    except (OSError, ValueError, KeyError):
        return {}
    return {rid: r["pose"] for rid, r in robots.items()}


def stood_still_s(run: Path, from_s: float) -> float | None:
    """Simulated time from ``from_s`` until a robot moved again (the simulator steps on while
    the server is away, its robots standing) [s]; None if none moved after it."""
    from mrslam.run_files import Gaps, read_truth

    truth = read_truth(run / "sim" / "truth.jsonl", Gaps(run))
    moved: list[float] = []
    for t in truth.values():
        stamps_s = t["stamps_ns"][1:] * 1e-9
        step_m = np.hypot(*np.diff(t["poses"][:, :2], axis=0).T)
        later = np.flatnonzero((stamps_s > from_s + 0.5) & (step_m > 1e-6))
        if len(later):
            moved.append(float(stamps_s[later[0]]))
    return round(min(moved) - from_s, 1) if moved else None


def score(run: Path, seen: dict[str, Any], base_poses: dict[str, list[float]] | None
          ) -> dict[str, Any]:
    try:
        report = json.loads((run / "report.json").read_text())
    except (OSError, ValueError):
        return {**seen, "report": False}
    row: dict[str, Any] = {
        **seen, "reached": report["reached"],
        "sim_time_to_threshold_s": report["sim_time_to_threshold_s"],
        "false_merges": report["false_merges"], "end": report["end"],
        "missing": report.get("missing", []),
        # the pose estimates against the truth: what a restart must not spoil
        "max_position_error_m": max((r.get("max_position_error_m") or 0.0
                                     for r in report.get("robots", {}).values()), default=None)}
    poses = final_poses(run)
    if base_poses is not None:
        common = sorted(set(poses) & set(base_poses))
        row["final_pose_max_diff_m"] = (round(max(
            float(np.hypot(poses[r][0] - base_poses[r][0], poses[r][1] - base_poses[r][1]))
            for r in common), 4) if common and len(common) == len(base_poses) else None)
    row["state_cost"] = state_cost(run, report)
    restarts = report.get("server_restarts", [])
    row["restarts"] = [{k: r.get(k) for k in (
        "sim_time_s", "signal", "restarted", "back_off_s", "coverage_before", "coverage_after",
        "up_after_s", "first_command_after_s")} for r in restarts]
    if restarts:
        r = restarts[0]
        kill_s = seen.get("killed_at_sim_s") or r["sim_time_s"]
        row["coverage_before"] = coverage_at(report, kill_s, after=False)
        row["coverage_after"] = coverage_at(report, kill_s, after=True)
        row["recovery_s"] = r.get("first_command_after_s")
        row["stood_still_sim_s"] = stood_still_s(run, kill_s)
    return row


def state_cost(run: Path, report: dict[str, Any]) -> dict[str, Any] | None:
    """What the journal and snapshots cost the last server of ``run``: bytes written per robot
    per second of robot data (at 10 Hz a simulated second is a second of scans), and their
    share of the server's CPU time."""
    try:
        summary = json.loads((run / "server" / "summary.json").read_text())
        j = summary["journal"]
        cpu_s = float(summary["cpu_s"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    robots = max(1, len(report.get("robots", {})))
    sim_s = max(1e-9, float(report.get("sim_time_s") or 0.0))
    written = j["bytes"] + j["snapshot_bytes_total"]
    return {"kb_per_robot_s": round(written / 1000.0 / robots / sim_s, 1),
            "journal_kb_per_robot_s": round(j["bytes"] / 1000.0 / robots / sim_s, 1),
            "cpu_fraction": round((j["journal_s"] + j["snapshot_s_total"]) / max(cpu_s, 1e-9),
                                  4),
            "snapshots": j["snapshots"], "snapshot_s_max": j["snapshot_s_max"]}


def goal_met(base: dict[str, Any], killed: list[dict[str, Any]]) -> dict[str, bool]:
    runs = [base, *killed]
    restarts_ok = all(k.get("restarts") for k in killed)

    def kept(k: dict[str, Any]) -> bool:
        before = k.get("coverage_before")
        after = k.get("coverage_after")
        return before is not None and after is not None and \
            after >= GOALS["coverage_kept"] * before

    return {
        "every_run_reaches_98pct_without_false_merges": all(
            r.get("reached") and r.get("false_merges") == 0 for r in runs),
        "coverage_after_restart_within_1pct": restarts_ok and all(kept(k) for k in killed),
        "final_poses_within_2cm": all(
            (k.get("final_pose_max_diff_m") is not None
             and k["final_pose_max_diff_m"] <= GOALS["final_pose_m"]) for k in killed),
        "recovery_within_5s": restarts_ok and all(
            k.get("recovery_s") is not None and k["recovery_s"] <= GOALS["recovery_s"]
            for k in killed),
        "state_within_50kb_per_robot_s_and_5pct_cpu": base.get("state_cost") is not None and (
            base["state_cost"]["kb_per_robot_s"] <= GOALS["kb_per_robot_s"]
            and base["state_cost"]["cpu_fraction"] <= GOALS["cpu_fraction"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=5, help="runs with the server killed")
    ap.add_argument("--window", type=float, nargs=2, default=(20.0, 80.0),
                    metavar=("FROM_S", "TO_S"), help="sim time range of the kill")
    ap.add_argument("--rng-seed", type=int, default=0, help="seed of the kill times")
    ap.add_argument("--out", type=Path, default=None, help="keep the run folders here")
    ap.add_argument("--scenario", default=None,
                    help="another scenario than the demo's default (e.g. large-house-5: the "
                    "large house, five robots, a large state to resume)")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="mrslam-recovery-"))
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.rng_seed)
    lo, hi = args.window
    kill_times = [round(float(t), 1) for t in rng.uniform(lo, hi, size=args.kills)]
    base_run = out / "uninterrupted"
    base = score(base_run, demo(base_run, None, args.scenario), None)
    base_poses = final_poses(base_run)
    killed = []
    for k, at_s in enumerate(kill_times):
        run = out / f"killed-{k}"
        killed.append(score(run, demo(run, at_s, args.scenario), base_poses))
    json.dump({"scenario": args.scenario or "small-house-3 (the demo's default)", "seed": 0,
               "kills": args.kills, "window_s": list(args.window), "out": str(out),
               "goals": GOALS, "uninterrupted": base, "killed": killed,
               "goal_met": goal_met(base, killed)}, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
