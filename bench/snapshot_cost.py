"""What a snapshot of the server's core costs the worker thread, at points along a mission.

The server snapshots its core every few seconds (``server.runtime.keeper``):
``Snapshots.begin`` runs on the worker thread, which serves no scan meanwhile (it forks a child
that pickles and writes; with ``--in-process`` it pickles there itself, as the server did
before), and ``Snapshots.finish`` on the writer thread (waits for the child, puts the snapshot
in place; in process: compresses, writes and syncs). This feeds the recorded tracks of
``bench.support.load_gen`` (robots wandering the large house at 10 Hz, each its own team, as
``bench/scan_cost.py`` does) into one ``ServerCore`` in process, and every ``--every`` steps
starts a snapshot into one state folder (sharing its blob store, as the server does), finished
on a thread while the scans go on. It prints, as JSON, per snapshot: the keyframes of all
robots, ``worker_ms`` (what ``begin`` held the worker), ``writer_ms`` (``finish``),
``pickle_and_write_ms`` (the child's, or in process the whole) and the bytes written; then
over the snapshots from step ``--late`` on: ``worker_ms`` p50/p99/max, and each step's wall
CPU time (all robots' scans, the worker thread's own) while a snapshot is being taken and
otherwise (what the copy-on-write costs the worker in page copies). Times ``_ms`` are wall
clock, ``_cpu_ms`` the thread's own CPU (on a busy machine wall time includes waiting for a
core). ``--profile`` profiles the last ``begin``; ``--check`` loads
the last snapshot back and compares the robots' keyframe poses with the live core's.

    python bench/snapshot_cost.py [--robots 10] [--steps 3000] [--every 50] [--late 1500]
                                  [--in-process] [--profile] [--check]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def run(robots: int, steps: int, every: int, late: int, profile: bool, check: bool,
        fork: bool, huge_pages: bool = False) -> dict[str, Any]:
    import numpy as np

    from bench.support.load_gen import make_tracks, pingpong
    from schemas import Scan
    from server.config import ServerConfig
    from server.core import ServerCore
    from server.runtime.hugepages import Collapser
    from server.runtime.snapshot import Pending, Snapshots
    from server.slam.field_cache import FIELDS

    tracks = make_tracks(600)
    core = ServerCore(ServerConfig.model_validate({"robots": None}))
    n_tracks = tracks.ranges_mm.shape[0]

    def scan(i: int, k: int) -> Scan:
        track, offset = i % n_tracks, (i * 37) % tracks.steps
        j = pingpong(k + offset, tracks.steps)
        return Scan(robot_id=f"r{i + 1}", seq=k, stamp_ns=(k + 1) * 100_000_000,
                    odom_pose=tuple(float(v) for v in tracks.odom[track, j]),
                    angle_min_rad=tracks.angle_min_rad,
                    angle_increment_rad=tracks.angle_increment_rad,
                    range_min_mm=tracks.range_min_mm, range_max_mm=tracks.range_max_mm,
                    ranges_mm=tracks.ranges_mm[track, j].tobytes())

    folder = Path(tempfile.mkdtemp(prefix="mrslam-snapcost-"))
    snaps = Snapshots(folder)
    snaps.use_fork = fork
    if huge_pages:
        snaps.huge_pages = Collapser()
    rows: list[dict[str, Any]] = []
    prof_out: list[dict[str, Any]] = []
    step_ms: list[tuple[float, bool]] = []     # each step's wall time, and whether a child ran
    writer: threading.Thread | None = None
    fed = 0
    t0 = time.perf_counter()

    def finish(job: Any, row: dict[str, Any]) -> None:
        w1 = time.perf_counter()
        snaps.finish(job)
        row["writer_ms"] = round((time.perf_counter() - w1) * 1e3, 2)
        row["snapshot_kb"] = round(snaps.last_bytes / 1024, 1)
        row["pickle_and_write_ms"] = round(snaps.last_seconds * 1e3, 2)
        if not isinstance(job, Pending):
            row["child_cpu_ms"] = round(snaps.last_cpu_s * 1e3, 2)
            if (pages := snaps.huge_pages) is not None and pages.unavailable is None:
                row["huge_pages_ms"] = round(pages.last_seconds * 1e3, 2)
        print(json.dumps(row), file=sys.stderr, flush=True)

    for k in range(steps):
        s0 = time.thread_time()
        for i in range(robots):
            s = scan(i, k)
            core.on_scan(s, s.stamp_ns)
            fed += 1
        step_ms.append(((time.thread_time() - s0) * 1e3,
                        writer is not None and writer.is_alive()))
        if (k + 1) % every:
            continue
        if writer is not None:
            writer.join()      # one snapshot at a time, as the server's keeper
        last = k + 1 == steps - steps % every or k + 1 == steps
        prof = cProfile.Profile() if profile and last else None
        w0, c0 = time.perf_counter(), time.thread_time()
        if prof is not None:
            prof.enable()
        job = snaps.begin(core, fed)
        if prof is not None:
            prof.disable()
        row = {"step": k + 1,
               "keyframes": sum(len(r.slam.keyframes) for r in core.robots.values()),
               "worker_ms": round((time.perf_counter() - w0) * 1e3, 2),
               "worker_cpu_ms": round((time.thread_time() - c0) * 1e3, 2),
               "rss_mb": _rss_mb(), "huge_mb": _huge_mb()}
        rows.append(row)
        if prof is not None:
            prof_out = _top(pstats.Stats(prof))
        writer = threading.Thread(target=finish, args=(job, row))
        writer.start()
    if writer is not None:
        writer.join()
    late_rows = [r for r in rows if r["step"] >= late] or rows
    held = np.array([r["worker_ms"] for r in late_rows])
    held_cpu = np.array([r["worker_cpu_ms"] for r in late_rows])
    wrote = np.array([r["pickle_and_write_ms"] for r in late_rows])
    during = [ms for ms, child in step_ms[late:] if child]
    other = [ms for ms, child in step_ms[late:] if not child]

    def pct(v: list[float] | Any, q: float) -> float | None:
        return round(float(np.percentile(v, q)), 2) if len(v) else None

    def mean(v: list[float]) -> float | None:
        return round(float(np.mean(v)), 2) if v else None

    out: dict[str, Any] = {
        "robots": robots, "steps": steps, "every": every, "late_from_step": late,
        "mode": "fork" if fork else "in process",
        "huge_pages": (None if snaps.huge_pages is None else
                       snaps.huge_pages.unavailable or "collapsed after each snapshot"),
        "wall_s": round(time.perf_counter() - t0, 1), "snapshots": rows,
        "late": {"snapshots": len(late_rows),
                 "worker_ms_p50": pct(held, 50), "worker_ms_p99": pct(held, 99),
                 "worker_ms_max": round(float(held.max()), 2),
                 "worker_cpu_ms_p50": pct(held_cpu, 50), "worker_cpu_ms_p99": pct(held_cpu, 99),
                 "worker_cpu_ms_max": round(float(held_cpu.max()), 2),
                 "pickle_and_write_ms_p50": pct(wrote, 50),
                 "pickle_and_write_ms_max": round(float(wrote.max()), 2),
                 "step_cpu_ms_mean_while_a_snapshot_is_taken": mean(during),
                 "step_cpu_ms_mean_otherwise": mean(other),
                 "steps_while_a_snapshot_is_taken": len(during)},
        "goal_worker_ms_max_10": bool(held.max() <= 10.0),
        # loop closure's likelihood fields (a cache shared by the robots, ``field_cache``)
        "fields": {"made": FIELDS.made, "reused": FIELDS.reused,
                   "held_mb": round(FIELDS.held_bytes / 2**20, 1)},
    }
    if prof_out:
        out["profile_last_prepare"] = prof_out
    if check:
        out["check"] = _check(core, folder)
    shutil.rmtree(folder, ignore_errors=True)     # the state folder was this run's alone
    return out


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    return float("nan")


def _huge_mb() -> float:
    """The process's anonymous memory in huge pages (what a fork copies cheaply)."""
    try:
        for line in Path("/proc/self/smaps_rollup").read_text().splitlines():
            if line.startswith("AnonHugePages:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return float("nan")


def _top(stats: pstats.Stats) -> list[dict[str, Any]]:
    raw: dict[Any, Any] = stats.stats  # type: ignore[attr-defined]
    rows = sorted(((tt, ct, nc, f"{Path(f).name}:{n}") for (f, _l, n), (_c, nc, tt, ct, _)
                   in raw.items()), reverse=True)[:15]
    return [{"function": name, "own_ms": round(tt * 1e3, 2), "cumulative_ms": round(ct * 1e3, 2),
             "calls": nc} for tt, ct, nc, name in rows]


def _check(core: Any, folder: Path) -> dict[str, Any]:
    """The last snapshot loaded back against the live core."""
    import numpy as np

    from server.runtime.snapshot import Snapshots

    t0 = time.perf_counter()
    loaded = Snapshots(folder).load()
    if loaded is None:
        return {"loaded": False}
    back = loaded[0]
    worst = 0.0
    same = set(back.robots) == set(core.robots)
    for rid, r in core.robots.items():
        a, b = r.slam.keyframe_poses(), back.robots[rid].slam.keyframe_poses()
        same &= a.shape == b.shape
        if a.shape == b.shape and len(a):
            worst = max(worst, float(np.abs(a - b).max()))
    return {"loaded": True, "load_s": round(time.perf_counter() - t0, 2), "same_robots": same,
            "keyframe_pose_diff_max": worst}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--steps", type=int, default=3000, help="10 Hz steps of every robot")
    ap.add_argument("--every", type=int, default=50, help="steps between snapshots")
    ap.add_argument("--late", type=int, default=1500, help="figures over snapshots from here")
    ap.add_argument("--profile", action="store_true", help="profile the last prepare")
    ap.add_argument("--check", action="store_true", help="load the last snapshot back")
    ap.add_argument("--in-process", action="store_true",
                    help="pickle on the worker (Snapshots.prepare), as before the fork")
    ap.add_argument("--huge-pages", action="store_true",
                    help="gather the server's memory into huge pages after each snapshot (not "
                         "the server's default)")
    a = ap.parse_args()
    print(json.dumps(run(a.robots, a.steps, a.every, a.late, a.profile, a.check,
                         not a.in_process, a.huge_pages), indent=1))


if __name__ == "__main__":
    main()
