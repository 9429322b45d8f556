"""Benchmark: SLAM on the real CARMEN logs, one fresh ``mrslam slam-log`` process per log.

Prints one JSON line per log: relation errors (Kümmerle et al. 2009; Cartographer's published
figures alongside), wall time including interpreter start-up and imports, data duration,
real-time ratio (data duration / wall time), and the peak resident memory of the child.
The child is pinned to one CPU core (and its math libraries to one thread).

    .venv/bin/python bench/slam_logs.py [--logs aces fr079 mit-csail] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data" / "carmen"
LOGS = ("aces", "fr079", "mit-csail")
# Hess et al., ICRA 2016, Table II: mean absolute translational [m] / rotational [deg] error
CARTOGRAPHER = {"aces": (0.0375, 0.373), "fr079": (0.0452, 0.538), "mit-csail": (0.0319, 0.369)}
GOAL_RATIO = 400.0       # issue 45: 400x real time on every log
GOAL_MEMORY_MB = 250.0   # issue 45: peak within 250 MB


@dataclass
class ChildRun:
    """One ``mrslam slam-log`` process: its exit code, output, wall and CPU time [s] and peak
    resident memory [MB]."""

    returncode: int
    stdout: str
    stderr: str
    wall_s: float
    cpu_s: float
    peak_mb: float


def run_child(log: Path, out: Path, core: int, config: Path | None = None,
              extra: Sequence[str] = (), root: Path = ROOT) -> ChildRun:
    """Run ``mrslam slam-log`` on ``log`` in a fresh process pinned to one CPU core (its math
    libraries to one thread), from the checkout at ``root`` (another commit's, to compare)."""
    cmd = [sys.executable, "-m", "mrslam", "slam-log", str(log), "--out", str(out), *extra]
    if config is not None:
        cmd += ["--config", str(config)]
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               TBB_NUM_THREADS="1")

    def pin() -> None:
        os.sched_setaffinity(0, {core})

    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, preexec_fn=pin)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    stdout = proc.stdout.read().decode() if proc.stdout else ""
    stderr = proc.stderr.read().decode() if proc.stderr else ""
    return ChildRun(os.waitstatus_to_exitcode(status), stdout, stderr, wall,
                    usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0)  # Linux: kB


def run_one(name: str, out: Path, core: int, config: Path | None) -> dict[str, object]:
    sys.path.insert(0, str(ROOT))
    from server.offline.evaluation import evaluate

    child = run_child(DATA / f"{name}.clf.bz2", out, core, config)
    if child.returncode != 0:
        return {"log": name, "error": f"exit {child.returncode}: {child.stderr.strip()[-500:]}"}
    summary = json.loads((out / "summary.json").read_text())
    res = evaluate(out / "poses.txt", DATA / f"{name}.relations")
    duration = float(summary["data_duration_s"])
    wall = child.wall_s
    ref_t, ref_r = CARTOGRAPHER[name]
    peak_mb = child.peak_mb
    return {
        "log": name,
        "trans_error_m": round(res.trans_mean_m, 4),
        "trans_error_std_m": round(res.trans_std_m, 4),
        "rot_error_deg": round(res.rot_mean_deg, 3),
        "rot_error_std_deg": round(res.rot_std_deg, 3),
        "relations_matched": res.matched,
        "relations_unmatched": res.unmatched,
        "cartographer_m_deg": [ref_t, ref_r],
        "accuracy_goal_met": res.trans_mean_m <= ref_t and res.rot_mean_deg <= ref_r,
        "wall_time_s": round(wall, 2),
        "cpu_time_s": round(child.cpu_s, 2),
        "slam_wall_time_s": round(float(summary["wall_time_s"]), 2),
        "data_duration_s": round(duration, 1),
        "realtime_ratio": round(duration / wall, 1),
        "speed_goal_met": duration / wall >= GOAL_RATIO,
        "peak_memory_mb": round(peak_mb, 1),
        "memory_goal_met": peak_mb <= GOAL_MEMORY_MB,
        "scans": summary["scans"],
        "keyframes": summary["keyframes"],
        "loop_closures": summary["loop_closures"],
        "cpu_core": core,
        "stdout": child.stdout.strip().splitlines()[-1] if child.stdout.strip() else "",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", nargs="+", default=list(LOGS), choices=LOGS)
    ap.add_argument("--keep", type=Path, help="keep the outputs in this folder")
    ap.add_argument("--core", type=int, default=0, help="CPU core to pin the child to")
    ap.add_argument("--config", type=Path, help="SLAM config YAML (default: built-in)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep or Path(tmp)
        for name in args.logs:
            out = base / name
            out.mkdir(parents=True, exist_ok=True)
            print(json.dumps(run_one(name, out, args.core, args.config)), flush=True)


if __name__ == "__main__":
    main()
