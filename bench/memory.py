"""Memory benchmark: resident memory against data time, for SLAM on the real logs and for the
server's core on a long simulated mission; prints JSON (one line per part, then a summary).

- ``logs``: for each CARMEN log of ``../shared/data/carmen``, a fresh child process runs what
  ``mrslam slam-log`` runs (read, SLAM scan by scan, export map and cloud), sampling its own
  resident memory (VmRSS) every ``--every-s`` of data time. Printed: the samples, the peak
  (``ru_maxrss``: the whole run, reading the log included), the steady RSS before the export
  and the highest RSS during it (``VmHWM`` reset just before), the export's rise over steady,
  the relation errors (Kümmerle et al. 2009) and the SLAM's CPU time. Also the highest
  ``RssAnon`` seen during the SLAM (``rss_anon_high_mb``: the process's own pages, sampled
  every 25 scans) and ``RssFile`` at its end (pages of mapped files: the libraries' code that
  is run; ``slam-log`` gives back the rest, ``server.offline.resident``). Goals: peak ≤ 250 MB,
  export rise ≤ 20 %. ``--long LOG N`` adds a long log made of a real one (``make_long_log``:
  N passes, forward and backward in time, as ROBOTLASER1 lines; not kept as data).
- ``mission``: a child process runs ``--robots`` robots of ``--scenario`` (default the large
  house) with the server's core in lockstep for ``--sim-hours`` of simulated time
  (``bench.support.mission``: explore, then patrol), sampling RSS every ``--every-s`` of
  simulated time. Per robot is (RSS − the process's RSS before the first step) / robots: what
  the server's state costs, without the interpreter, the libraries and the simulator. At the
  end it exports every team's map as the server does (``server.runtime.outputs``) and reports the
  export's rise as above. Goal: ≤ 300 MB per robot after two hours, growing sub-linearly once
  the building is explored (``growth_last_half``: MB per robot-hour over the second half,
  against the first half's).

    python bench/memory.py [--only logs|mission] [--logs aces fr079 mit-csail] [--long aces 4]
                           [--robots 3] [--sim-hours 2] [--every-s 60] [--no-reuse]
                           [--scenario NAME] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
ROOT = _HERE.parent
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data" / "carmen"
LOGS = ("aces", "fr079", "mit-csail")
GOAL_PEAK_MB = 250.0
GOAL_ROBOT_MB = 300.0
GOAL_EXPORT_RISE = 0.20


def rss_mb(field: str = "VmRSS") -> float:
    """This process's resident memory [MB] (``VmHWM``: the highest since the last reset)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def reset_peak() -> None:
    """Make ``VmHWM`` start again from the current RSS (Linux ``clear_refs`` 5)."""
    Path("/proc/self/clear_refs").write_text("5")


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def export_rise(write: Any) -> dict[str, float]:
    """Steady RSS, then the highest RSS while ``write()`` runs; and the run's highest RSS
    before it (``run_peak_mb``: resetting ``VmHWM`` resets ``ru_maxrss`` too)."""
    run_peak = rss_mb("VmHWM")
    steady = rss_mb()
    reset_peak()
    t0 = time.perf_counter()
    write()
    high = rss_mb("VmHWM")
    return {"run_peak_mb": round(run_peak, 1), "steady_mb": round(steady, 1),
            "export_peak_mb": round(high, 1),
            "export_rise": round(high / steady - 1.0, 3),
            "export_s": round(time.perf_counter() - t0, 2)}


# ---------------------------------------------------------------------------------------------
# children


def keyframe_bytes(keyframes: Any) -> dict[str, float]:
    """What keyframes hold in memory (matching points, normals, ranges; map points kept in
    memory) and what they keep on disk (``server.slam.render_store``) [MB]."""
    mem = disk = 0
    for kf in keyframes:
        m = kf.matchable
        mem += m.points.nbytes + m.normals.nbytes + m.ranges_m.nbytes + kf.render.nbytes
        if kf.render.on_disk:
            disk += 8 * (kf.render.n_hits + kf.render.n_misses)
    return {"keyframes_in_memory_mb": round(mem / 2**20, 2),
            "keyframes_on_disk_mb": round(disk / 2**20, 2)}


def log_path(name: str, out: Path) -> Path:
    """The log file of ``name``: a real one, or a long one made by ``make_long_log``."""
    made = out / f"{name}.clf"
    return made if made.exists() else DATA / f"{name}.clf.bz2"


def make_long_log(name: str, passes: int, out: Path) -> tuple[str, float]:
    """A long log made of a real one: ``passes`` passes, alternately forward and backward in
    time (so that the odometry never jumps), each pass's stamps after the last's, every scan
    written as a ROBOTLASER1 line (the format of the long logs of CARMEN's robots: beam
    geometry and both poses on each line; no ODOM lines). Returns its name and duration [s]."""
    import bz2
    import math

    from server.offline.logs.carmen import guess_beam_angles

    rows = []
    with bz2.open(DATA / f"{name}.clf.bz2", "rt") as f:
        for line in f:
            w = line.split()
            if w and w[0] == "FLASER":
                n = int(w[1])
                rows.append((float(w[8 + n]), n, " ".join(w[2:2 + n]), " ".join(w[2 + n:8 + n])))
    t0, t1 = rows[0][0], rows[-1][0]
    span = t1 - t0 + (t1 - t0) / max(len(rows) - 1, 1)
    long_name = f"{name}-x{passes}"
    with open(out / f"{long_name}.clf", "w") as f:
        for p in range(passes):
            for stamp, n, ranges, poses in (rows if p % 2 == 0 else rows[::-1]):
                t = t0 + p * span + (stamp - t0 if p % 2 == 0 else t1 - stamp)
                a = guess_beam_angles(n)
                res = float(a[1] - a[0]) if n > 1 else math.pi
                f.write(f"ROBOTLASER1 0 {a[0]:.12f} {res * (n - 1):.12f} {res:.12f} 0 0.01 0 "
                        f"{n} {ranges} 0 {poses} 0 0 0 0 0 {t:.6f} bench {t:.6f}\n")
    return long_name, passes * span


def child_log(name: str, out: Path, every_s: float) -> dict[str, Any]:
    # as ``mrslam slam-log``: its import readies numba without SciPy's BLAS
    from server.offline.slam_log import Drawing, SlamLogConfig, freed, process, read_recording
    from server.slam.export import write_nav2, write_ply

    cfg = SlamLogConfig()
    # as ``mrslam slam-log``: the scans read without their ranges, which are read again from
    # the file as the scans are fed, and each scan freed once fed
    rec = read_recording(log_path(name, out.parent), cfg, stream=True)
    scans = rec.scans      # packed (``server.offline.packed``), the records freed
    freed()
    after_read = rss_mb()
    stamps_s = [s.record.stamp_s for s in scans]
    t_first = stamps_s[0]
    n_scans = len(scans)
    samples: list[list[float]] = []
    anon: list[float] = [rss_mb("RssAnon")]   # the process's own pages (no file's), sampled
    next_t = [0.0]

    def progress(i: int) -> None:
        t = stamps_s[i] - t_first
        anon[0] = max(anon[0], rss_mb("RssAnon"))
        if t >= next_t[0]:
            samples.append([round(t, 1), round(rss_mb(), 1)])
            next_t[0] = t + every_s

    cpu0 = time.process_time()
    slam, stamps, _, _ = process(scans, cfg.slam, progress, release=True,
                                 ranges_of=rec.lines.ranges if rec.lines else None)
    cpu = time.process_time() - cpu0
    samples.append([round(stamps_s[-1] - t_first, 1), round(rss_mb(), 1)])
    out.mkdir(parents=True, exist_ok=True)
    _, poses = slam.scan_poses()
    with open(out / "poses.txt", "w") as f:
        for text, (x, y, th) in zip(stamps, poses, strict=True):
            f.write(f"{text} {x:.6f} {y:.6f} {th:.6f}\n")
    held = keyframe_bytes(slam.keyframes)
    # as ``mrslam slam-log``: the SLAM freed, the map and cloud drawn from what they need
    drawing = Drawing.of(slam)
    del slam
    freed()
    grid = drawing.grid()

    def write() -> None:
        write_nav2(grid, out, "map")
        write_ply(out / "cloud.ply", drawing.cloud())

    exp = export_rise(write)
    anon[0] = max(anon[0], rss_mb("RssAnon"))
    return {"rss_after_read_mb": round(after_read, 1), "samples_t_s_rss_mb": samples,
            "rss_anon_high_mb": round(anon[0], 1), "rss_file_end_mb": round(rss_mb("RssFile"), 1),
            "slam_cpu_s": round(cpu, 1), "scans": n_scans, "keyframes": len(drawing.keyframes),
            **held,
            "map_cells": grid.shape, "map_tiles": getattr(grid, "tiles", None),
            "map_mb": round(getattr(grid, "nbytes", 6 * grid.shape[0] * grid.shape[1]) / 2**20,
                            2), **exp, "peak_mb": round(max(peak_mb(), exp["run_peak_mb"]), 1)}


def child_mission(scenario: str, robots: int, sim_hours: float, every_s: float,
                  out: Path, reuse: bool) -> dict[str, Any]:
    from bench.support.mission import scenario_mission
    from server.runtime.outputs import write_nav2_grid

    def keyframes(data: dict[str, Any]) -> dict[str, Any]:
        return {**data, "slam": {**data["slam"], "keyframes": {"reuse": reuse}}}

    mission = scenario_mission(scenario, robots, config=keyframes)
    base = rss_mb()
    samples: list[list[float]] = []
    end_s = sim_hours * 3600.0
    next_t = 0.0
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    while mission.sim_time_s < end_s:
        mission.step()
        if mission.sim_time_s >= next_t:
            samples.append([round(mission.sim_time_s), round(rss_mb(), 1)])
            next_t += every_s
            print(json.dumps({"sim_s": samples[-1][0], "rss_mb": samples[-1][1],
                              "wall_s": round(time.perf_counter() - t0)}),
                  file=sys.stderr, flush=True)
    core = mission.core
    samples.append([round(mission.sim_time_s), round(rss_mb(), 1)])

    def write() -> None:
        for tid in core.teams:
            write_nav2_grid(core.planning_grid(tid), out / tid)

    exp = export_rise(write)
    kf = {rid: len(r.slam.keyframes) for rid, r in core.robots.items()}
    reused = {rid: r.slam.stats.reused for rid, r in core.robots.items()}
    return {"base_mb": round(base, 1), "samples_t_s_rss_mb": samples,
            "wall_s": round(time.perf_counter() - t0, 1),
            "cpu_s": round(time.process_time() - cpu0, 1), "patrols": mission.patrols,
            "teams": len(core.teams), "keyframes": kf, "reused": reused,
            **keyframe_bytes(kf for r in core.robots.values() for kf in r.slam.keyframes), **exp,
            "peak_mb": round(max(peak_mb(), exp["run_peak_mb"]), 1)}


# ---------------------------------------------------------------------------------------------
# parent


def run_child(args: list[str]) -> dict[str, Any]:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, __file__, "--child", *args], cwd=ROOT, env=env,
                          stdout=subprocess.PIPE, text=True, check=False)
    if proc.returncode != 0:
        return {"error": f"child exit {proc.returncode}"}
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def logs_part(names: list[str], every_s: float, out: Path) -> list[dict[str, Any]]:
    from server.offline.evaluation import evaluate

    rows = []
    for name in names:
        if not log_path(name, out).exists():
            rows.append({"log": name, "error": f"{DATA / name}.clf.bz2 not found"})
            continue
        res = run_child(["log", name, str(out / name), str(every_s)])
        if "error" not in res and (DATA / f"{name}.relations").exists():
            ev = evaluate(out / name / "poses.txt", DATA / f"{name}.relations")
            res.update(trans_error_m=round(ev.trans_mean_m, 4),
                       rot_error_deg=round(ev.rot_mean_deg, 3))
        if "error" not in res:
            res.update(peak_goal_met=res["peak_mb"] <= GOAL_PEAK_MB,
                       export_goal_met=res["export_rise"] <= GOAL_EXPORT_RISE)
        row = {"part": "logs", "log": name, **res}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def mission_part(scenario: str, robots: int, sim_hours: float, every_s: float,
                 out: Path, reuse: bool) -> dict[str, Any]:
    res = run_child(["mission", scenario, str(robots), str(sim_hours), str(every_s),
                     str(out / "mission"), "reuse" if reuse else "no-reuse"])
    row: dict[str, Any] = {"part": "mission", "scenario": scenario, "robots": robots,
                           "sim_hours": sim_hours, "keyframe_reuse": reuse, **res}
    if "error" not in res:
        s = res["samples_t_s_rss_mb"]
        per_robot = [[t, round((m - res["base_mb"]) / robots, 1)] for t, m in s]
        row["per_robot_mb"] = per_robot
        row["per_robot_end_mb"] = per_robot[-1][1]
        half = len(per_robot) // 2
        hours = (per_robot[-1][0] - per_robot[half][0]) / 3600.0

        def rate(a: list[float], b: list[float]) -> float:
            h = (b[0] - a[0]) / 3600.0
            return round((b[1] - a[1]) / h, 1) if h > 0 else float("nan")

        if hours > 0:
            row["growth_first_half_mb_per_robot_hour"] = rate(per_robot[0], per_robot[half])
            row["growth_last_half_mb_per_robot_hour"] = rate(per_robot[half], per_robot[-1])
        row["robot_goal_met"] = per_robot[-1][1] <= GOAL_ROBOT_MB and sim_hours >= 2.0
        row["export_goal_met"] = res["export_rise"] <= GOAL_EXPORT_RISE
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        kind, rest = sys.argv[2], sys.argv[3:]
        if kind == "log":
            res = child_log(rest[0], Path(rest[1]), float(rest[2]))
        else:
            res = child_mission(rest[0], int(rest[1]), float(rest[2]), float(rest[3]),
                                Path(rest[4]), rest[5] == "reuse")
        print(json.dumps(res))
        return
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", choices=["logs", "mission"], default=None)
    ap.add_argument("--logs", nargs="+", default=list(LOGS))
    ap.add_argument("--long", nargs=2, metavar=("LOG", "PASSES"), default=None,
                    help="also a long log made of LOG: PASSES passes, forward and backward "
                         "(make_long_log), written into the output folder")
    ap.add_argument("--scenario", default="large-house-5")
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--sim-hours", type=float, default=2.0)
    ap.add_argument("--every-s", type=float, default=60.0)
    ap.add_argument("--reuse", action=argparse.BooleanOptionalAction, default=True,
                    help="slam.keyframes.reuse in the mission (default: on, as the server)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    out = a.out or Path(tempfile.mkdtemp(prefix="mrslam-memory-"))
    summary: dict[str, Any] = {"out": str(out)}
    if a.only in (None, "logs"):
        names = list(a.logs)
        if a.long:
            out.mkdir(parents=True, exist_ok=True)
            long_name, seconds = make_long_log(a.long[0], int(a.long[1]), out)
            summary["long_log"] = {"name": long_name, "duration_min": round(seconds / 60, 1)}
            names.append(long_name)
        rows = logs_part(names, a.every_s, out)
        ok = [r for r in rows if "error" not in r]
        summary["logs_peak_mb_max"] = max((r["peak_mb"] for r in ok), default=None)
        summary["logs_goal_met"] = bool(ok) and len(ok) == len(rows) and all(
            r["peak_goal_met"] and r["export_goal_met"] for r in ok)
    if a.only in (None, "mission"):
        row = mission_part(a.scenario, a.robots, a.sim_hours, a.every_s, out, a.reuse)
        summary["mission_per_robot_end_mb"] = row.get("per_robot_end_mb")
        summary["mission_goal_met"] = bool(row.get("robot_goal_met")) and bool(
            row.get("export_goal_met"))
    print(json.dumps({"summary": summary}), flush=True)


if __name__ == "__main__":
    main()
