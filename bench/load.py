"""Load benchmark: N robots at 10 Hz against a real ``mrslam server`` over Zenoh on loopback.

For each N of a rising series a fresh server process starts (``bench.support.fleet``, default
configuration), and generator processes (``bench.support.load_gen``, one per
``--robots-per-process`` robots) make N robots that look like agents to it: liveliness token,
``cmd_vel`` subscription, 10 Hz scans replaying tracks recorded once from the simulator (the
large house, a reactive wanderer), each robot with its own id, seq, stamps and an offset into the
tracks. After ``--warmup-s`` the bench measures for ``--window-s``:

- ``scan_to_command_p50_ms`` / ``_p99_ms``: from publishing a scan to receiving the
  ``VelocityCommand`` that answers it (the server stamps a command with its scan's own stamp), in
  the generator process, over the scans sent in the window that were answered at all;
- ``dropped_scan_fraction``: the larger of (a) the window's scans without an answer within
  ``--answer-timeout-s`` and (b) the server's own ``dropped_scans`` over all the scans it accepted
  in the run (its ``summary.json``); both are reported;
- ``server_cpu_cores``: utime+stime of the server and its descendants over the window, per wall
  second; ``server_rss_mb`` (VmRSS at the window's end, the whole process tree) and its peak;
- ``server_cpu_ms_per_scan``: that CPU per scan received (issue 45's measure), and
  ``server_cpu_split_cores``: the server's busiest thread (the worker handling the scans), its
  other threads (Zenoh's, the writer's) and its child processes (planners, map matching);
- the generators' own rate: a run whose slowest robot sent below 95 % of the rate is invalid.

With ``--workers K`` the server is split over K worker processes (``server.runtime.cluster``):
worker 0 is the router the robots connect to, the others connect to it; CPU and memory are
summed over all of them, and each run lists how many robots each worker served.

The series stops after the first N that fails both limits widely (p99 over ``WIDE`` × the limit
and dropped over ``WIDE`` × the limit). ``capacity_robots`` is the largest valid N with
p99 ≤ 100 ms and ≤ 1 % dropped (null when none).

    python bench/load.py [--robots 5 10 20 ...] [--warmup-s 5] [--window-s 20] [--quick]
                         [--keep-going] [--out DIR] [--server-config server.yaml]
                         [--workers K]

Prints one JSON object. The machine's cores are shared between the server and the generators;
the generators' CPU is reported beside the server's.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
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
ROOT = _HERE.parent

from bench.support.fleet import ServerProcess  # noqa: E402
from bench.support.load_gen import Tracks, make_tracks  # noqa: E402
from schemas import keys  # noqa: E402

P99_LIMIT_MS = 100.0
DROP_LIMIT = 0.01
RATE_MIN_SHARE = 0.95     # a generator below this share of the rate makes the run invalid
WIDE = 3.0                # "fails by a wide margin": this many times over both limits
DEFAULT_SERIES = [1, 2, 3, 5, 7, 10, 15, 20, 30, 40, 50, 60, 80]
QUICK_SERIES = [2, 4]


# -- the server's process tree ------------------------------------------------------------------
_TICK = os.sysconf("SC_CLK_TCK")


def _stat(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2:].split()   # fields from 3 (state) on


def process_tree(pid: int) -> list[int]:
    """``pid`` and its live descendants."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            st = _stat(int(d.name))
            if st is not None:
                children.setdefault(int(st[1]), []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def tree_cpu_s(pid: int) -> float:
    """utime+stime of ``pid`` and its live descendants, plus their reaped children's."""
    total = 0.0
    for p in process_tree(pid):
        st = _stat(p)
        if st is not None:   # utime stime cutime cstime are fields 14-17
            total += sum(int(x) for x in st[11:15]) / _TICK
    return total


def threads_cpu_s(pid: int) -> dict[int, float]:
    """utime+stime of each thread of ``pid`` (by thread id)."""
    out: dict[int, float] = {}
    try:
        tids = [int(t.name) for t in Path(f"/proc/{pid}/task").iterdir()]
    except OSError:
        return out
    for tid in tids:
        try:
            text = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue
        f = text[text.rindex(")") + 2:].split()
        out[tid] = (int(f[11]) + int(f[12])) / _TICK
    return out


def cpu_split(pids: list[int], before: dict[tuple[int, int], float],
              after: dict[tuple[int, int], float], tree: float, wall: float
              ) -> dict[str, float]:
    """Where the servers' CPU went over the window, in cores: each server's busiest thread
    (the worker that handles the scans), its other threads (Zenoh's, the writer's), and its
    child processes (the planners, map matching, snapshots)."""
    per = {k: v - before.get(k, 0.0) for k, v in after.items()}
    busiest = sum(max((v for (p, _), v in per.items() if p == pid), default=0.0)
                  for pid in pids)
    own = sum(per.values())
    return {"busiest_thread": round(busiest / wall, 3),
            "other_threads": round((own - busiest) / wall, 3),
            "child_processes": round(max(0.0, tree - own) / wall, 3)}


def machine_busy_s() -> float:
    """CPU seconds the whole machine spent busy (all cores; /proc/stat)."""
    f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:8]]
    return (sum(f) - f[3] - f[4]) / _TICK   # less idle and iowait


def tree_rss_mb(pid: int) -> float:
    total = 0.0
    for p in process_tree(pid):
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024
        except OSError:
            pass
    return total


# -- one N ---------------------------------------------------------------------------------------
def _read_json_line(proc: subprocess.Popen[str], timeout_s: float) -> dict[str, Any]:
    import select

    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    line = proc.stdout.readline() if ready else ""
    if not line:
        raise RuntimeError(f"generator {proc.pid} said nothing (exit code {proc.poll()})")
    return dict(json.loads(line))


def _percentile(values: np.ndarray, q: float) -> float | None:
    return round(float(np.percentile(values, q)), 2) if len(values) else None


def run_one(n: int, args: argparse.Namespace, tracks_path: Path, n_tracks: int, steps: int,
            folder: Path) -> dict[str, Any]:
    folder.mkdir(parents=True, exist_ok=True)
    config = yaml.safe_load(Path(args.server_config).read_text()) if args.server_config else {}
    servers = start_servers(folder, config, args.workers)
    srv = servers[0]
    gens: list[subprocess.Popen[str]] = []
    results: list[dict[str, Any]] = []
    cpu = rss_end = rss_peak = busy = 0.0
    period = 1.0 / args.rate_hz
    try:
        n_procs = max(1, math.ceil(n / args.robots_per_process))
        robots = [[f"L{i:03d}", i % n_tracks, (i // n_tracks) * 173 % (2 * steps - 2),
                   period * i / n] for i in range(n)]
        for p in range(n_procs):
            g = subprocess.Popen(
                [sys.executable, "-m", "bench.support.load_gen"], cwd=ROOT, text=True,
                stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                stderr=open(folder / f"generator_{p}.log", "w"),  # noqa: SIM115
                env={**os.environ, "PYTHONPATH": str(ROOT)})
            gens.append(g)
            assert g.stdin is not None
            g.stdin.write(json.dumps({
                "endpoint": srv.endpoint, "robots": robots[p::n_procs],
                "tracks": str(tracks_path), "rate_hz": args.rate_hz,
                "answer_timeout_s": args.answer_timeout_s}) + "\n")
            g.stdin.flush()
        for g in gens:
            _read_json_line(g, 60.0)   # ready
        t_start = time.monotonic() + 0.5
        t_measure = t_start + args.warmup_s
        t_end = t_measure + args.window_s
        window_unix = time.time() + (t_measure - time.monotonic())
        for g in gens:
            assert g.stdin is not None
            g.stdin.write(json.dumps({"t_start": t_start, "t_measure": t_measure,
                                      "t_end": t_end}) + "\n")
            g.stdin.flush()
        time.sleep(max(0.0, t_measure - time.monotonic()))
        pids = [sp.proc.pid for sp in servers]

        def cpu_s() -> float:
            return sum(tree_cpu_s(p) for p in pids)

        def rss() -> float:
            return sum(tree_rss_mb(p) for p in pids)

        def threads() -> dict[tuple[int, int], float]:
            return {(p, t): v for p in pids for t, v in threads_cpu_s(p).items()}

        th0 = threads()
        cpu0, busy0, w0 = cpu_s(), machine_busy_s(), time.monotonic()
        while time.monotonic() < t_end:
            rss_peak = max(rss_peak, rss())
            time.sleep(min(0.5, max(0.0, t_end - time.monotonic())))
        wall = time.monotonic() - w0
        cpu_tree = cpu_s() - cpu0
        split = cpu_split(pids, th0, threads(), cpu_tree, wall)
        cpu = cpu_tree / wall
        busy = (machine_busy_s() - busy0) / wall
        rss_end = rss()
        rss_peak = max(rss_peak, rss_end)
        for g in gens:
            results.append(_read_json_line(g, args.answer_timeout_s + 60.0))
            g.wait(timeout=30)
    finally:
        for g in gens:
            if g.poll() is None:
                g.kill()
                g.wait()
        codes = [sp.stop() for sp in servers]
    summaries = []
    for sp in servers:
        path = sp.folder / "server" / "summary.json"
        summaries.append(json.loads(path.read_text()) if path.exists() else {})
    summary = dict(summaries[0])    # every worker admits every robot: its registry counts all
    summary["dropped_scans"] = {f"{w}:{k}": v for w, sm in enumerate(summaries)
                                for k, v in sm.get("dropped_scans", {}).items()}
    summary["errors"] = sum(sm.get("errors") or 0 for sm in summaries)
    code = max(codes, key=abs)
    run = summarise(n, n_procs, results, cpu, rss_end, rss_peak, summary, code, args)
    # to line up slow_moments with a profile or a log of the server's taken meanwhile
    run["window_start_unix"] = round(window_unix, 3)
    run["server_pids"] = pids
    if len(servers) > 1:
        run["workers"] = [{"worker": w, "robots_served": len(c.get("robots_served", [])),
                           **{k: c.get(k, 0) for k in ("claimed", "asked", "given",
                                                       "conflicts_lost")}}
                          for w, c in enumerate(sm.get("cluster") or {} for sm in summaries)]
    # the goal's measure: the server's CPU per scan, and where it went
    run["server_cpu_ms_per_scan"] = round(cpu / (n * args.rate_hz) * 1e3, 3)
    run["server_cpu_split_cores"] = split
    # everything else on the machine meanwhile (other users' work competes for the cores)
    run["machine_busy_cores"] = round(busy, 3)
    run["git_commit"] = git_state()["commit"]   # others commit while the series runs
    run["other_busy_cores"] = round(max(0.0, busy - cpu - run["generator"]["cpu_cores"]), 3)
    return run


def start_servers(folder: Path, config: dict[str, Any], workers: int) -> list[ServerProcess]:
    """One server, up; or ``workers`` worker processes of one (``server.runtime.cluster``),
    all up and seeing each other: worker 0 is the Zenoh router the robots connect to, the others its
    clients (started once it listens)."""
    if workers <= 1:
        srv = ServerProcess(folder, config)
        try:
            srv.client(timeout_s=60.0).close()   # up: its liveliness token seen
        except BaseException:
            srv.stop()
            raise
        return [srv]
    for w in range(workers):
        (folder / f"worker{w}").mkdir(parents=True, exist_ok=True)
    first = ServerProcess(folder / "worker0", {**config, "cluster": {"worker": 0}})
    out = [first]
    bus = first.client(timeout_s=60.0)
    try:
        seen: set[str] = set()
        bus.watch_alive(keys.ALL_CLUSTER_WORKERS, lambda k, alive: seen.add(k))
        for w in range(1, workers):
            sp = ServerProcess(folder / f"worker{w}", {
                **config, "cluster": {"worker": w},
                "bus": {"mode": "client", "listen": [], "connect": [first.endpoint]}})
            sp.endpoint = first.endpoint    # reached through the router
            out.append(sp)
        deadline = time.monotonic() + 60.0
        while len(seen) < workers:
            if time.monotonic() > deadline or any(sp.proc.poll() is not None for sp in out):
                raise RuntimeError(f"only workers {sorted(seen)} came up")
            time.sleep(0.1)
        time.sleep(1.0)    # and each other's
    except BaseException:
        for sp in out:
            sp.stop()
        raise
    finally:
        bus.close()
    return out


def slow_moments(gens: list[dict[str, Any]], limit_ms: float = P99_LIMIT_MS,
                 bin_s: float = 0.5) -> list[list[float]]:
    """The moments (s into the window, by ``bin_s``) when answers took over ``limit_ms``:
    how many scans each, and the slowest; the ten slowest moments, in time order. A pause of
    the server's own (a snapshot, the outputs, a decision) holds every robot at once."""
    bins: dict[float, list[float]] = {}
    for g in gens:
        for t, ms in g.get("slowest", []):
            if ms > limit_ms:
                bins.setdefault(round(t // bin_s * bin_s, 2), []).append(ms)
    worst = sorted(bins.items(), key=lambda kv: -max(kv[1]))[:10]
    return [[t, len(v), max(v)] for t, v in sorted(worst)]


def summarise(n: int, n_procs: int, gens: list[dict[str, Any]], cpu: float, rss_end: float,
              rss_peak: float, summary: dict[str, Any], code: int,
              args: argparse.Namespace) -> dict[str, Any]:
    lat = np.array([v for g in gens for v in g["latencies_ms"]])
    sent = sum(g["sent"] for g in gens)
    no_answer = sum(g["unanswered"] + g["answered_late"] for g in gens)
    own = no_answer / sent if sent else 1.0
    reg = summary.get("registry", {})
    accepted = sum(r.get("accepted_scan", 0) for r in reg.values())
    dropped = sum(v for k, v in summary.get("dropped_scans", {}).items()
                  if not k.startswith("#"))
    server_frac = dropped / accepted if accepted else None
    fraction = max(own, server_frac or 0.0)
    p99 = _percentile(lat, 99)
    rate_min = min((g["rate_hz_min"] for g in gens), default=0.0)
    valid = rate_min >= RATE_MIN_SHARE * args.rate_hz
    ok = valid and p99 is not None and p99 <= P99_LIMIT_MS and fraction <= DROP_LIMIT
    return {
        "robots": n,
        "scan_to_command_p50_ms": _percentile(lat, 50),
        "scan_to_command_p99_ms": p99,
        "dropped_scan_fraction": round(fraction, 4),
        "server_cpu_cores": round(cpu, 3),
        "server_rss_mb": round(rss_end, 1),
        "server_rss_peak_mb": round(rss_peak, 1),
        "ok": ok, "valid": valid,
        "scan_to_command_p90_ms": _percentile(lat, 90),
        "scan_to_command_max_ms": round(float(lat.max()), 2) if len(lat) else None,
        "scans_sent": sent, "scans_answered": len(lat),
        "unanswered_fraction": round(own, 4),
        "server_dropped_scans": dropped, "server_accepted_scans": accepted,
        "server_dropped_fraction": None if server_frac is None else round(server_frac, 4),
        "slow_moments": slow_moments(gens),
        "server_errors": summary.get("errors"),
        "server_refused": summary.get("admission", {}).get("refused"),
        "server_exit_code": code,
        "unmatched_commands": sum(g["unmatched_commands"] for g in gens),
        "generator": {
            "processes": n_procs,
            "rate_hz_min": rate_min,
            "rate_hz_mean": round(float(np.mean([g["rate_hz_mean"] for g in gens])), 3)
            if gens else 0.0,
            "send_lateness_p99_ms": max((g["send_lateness_p99_ms"] for g in gens), default=None),
            "cpu_cores": round(sum(g["cpu_cores"] for g in gens), 3),
        },
    }


def far_off(run: dict[str, Any]) -> bool:
    """Fails both limits by a wide margin: no point in more robots."""
    p99 = run["scan_to_command_p99_ms"]
    return (p99 is None or p99 > WIDE * P99_LIMIT_MS) and \
        run["dropped_scan_fraction"] > WIDE * DROP_LIMIT


def git_state() -> dict[str, Any]:
    def git(*a: str) -> str:
        r = subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True)
        return r.stdout.strip()

    return {"commit": git("rev-parse", "HEAD"),
            "server_changes_not_committed": git("status", "--porcelain", "--", "server",
                                                 "schemas", "factors").splitlines()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", type=int, nargs="+", default=None,
                    help=f"the series of N (default {DEFAULT_SERIES})")
    ap.add_argument("--warmup-s", type=float, default=None, help="default 5 (quick: 3)")
    ap.add_argument("--window-s", type=float, default=None, help="default 20 (quick: 5)")
    ap.add_argument("--rate-hz", type=float, default=10.0)
    ap.add_argument("--answer-timeout-s", type=float, default=1.0,
                    help="a scan not answered within this counts as dropped")
    ap.add_argument("--robots-per-process", type=int, default=25)
    ap.add_argument("--workers", type=int, default=1,
                    help="split the server over this many worker processes "
                    "(server.runtime.cluster)")
    ap.add_argument("--track-steps", type=int, default=1200,
                    help="length of the recorded tracks, in LIDAR periods")
    ap.add_argument("--server-config", default=None,
                    help="YAML merged into the server's defaults")
    ap.add_argument("--keep-going", action="store_true",
                    help="run the whole series even after the server fell far behind")
    ap.add_argument("--quick", action="store_true",
                    help=f"a smoke run: N in {QUICK_SERIES}, 3 s warm-up, 5 s windows")
    ap.add_argument("--out", default=None, help="keep the runs' folders here")
    args = ap.parse_args()
    series = args.robots or (QUICK_SERIES if args.quick else DEFAULT_SERIES)
    if args.warmup_s is None:
        args.warmup_s = 3.0 if args.quick else 5.0
    if args.window_s is None:
        args.window_s = 5.0 if args.quick else 20.0
    if args.quick and args.track_steps == 1200:
        args.track_steps = 300

    with tempfile.TemporaryDirectory(prefix="mrslam-load-") as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        tracks = make_tracks(args.track_steps)
        tracks_path = out / "tracks.npz"
        tracks.save(tracks_path)
        tracks_s = time.monotonic() - t0
        assert Tracks.load(tracks_path).steps == args.track_steps
        runs: list[dict[str, Any]] = []
        for n in sorted(series):
            run = run_one(n, args, tracks_path, tracks.ranges_mm.shape[0], tracks.steps,
                          out / f"n{n:03d}")
            runs.append(run)
            print(f"N={n}: p50 {run['scan_to_command_p50_ms']} ms, p99 "
                  f"{run['scan_to_command_p99_ms']} ms, dropped {run['dropped_scan_fraction']}, "
                  f"server {run['server_cpu_cores']} cores, {run['server_rss_mb']} MB, "
                  f"generator {run['generator']['rate_hz_min']} Hz min, "
                  f"others {run['other_busy_cores']} cores"
                  f"{'' if run['valid'] else ' (INVALID)'}", file=sys.stderr, flush=True)
            if far_off(run) and not args.keep_going:
                break
    passing = [r["robots"] for r in runs if r["ok"]]
    by_drops = [r["robots"] for r in runs
                if r["valid"] and r["dropped_scan_fraction"] <= DROP_LIMIT]
    print(json.dumps({
        "runs": runs,
        "capacity_robots": max(passing) if passing else None,
        # the same without the latency limit: how many robots are served at all
        "capacity_robots_drops_only": max(by_drops) if by_drops else None,
        "cores": os.cpu_count(),
        "limits": {"p99_ms": P99_LIMIT_MS, "dropped_fraction": DROP_LIMIT,
                   "generator_rate_hz_min": RATE_MIN_SHARE * args.rate_hz},
        "settings": {"robots": series, "warmup_s": args.warmup_s, "window_s": args.window_s,
                     "rate_hz": args.rate_hz, "answer_timeout_s": args.answer_timeout_s,
                     "robots_per_process": args.robots_per_process, "workers": args.workers,
                     "track_steps": args.track_steps, "server_config": args.server_config,
                     "keep_going": args.keep_going, "quick": args.quick,
                     "tracks": f"large house, {tracks.ranges_mm.shape[0]} robots x "
                               f"{tracks.steps} steps, replayed back and forth",
                     "tracks_s": round(tracks_s, 2)},
        "git": git_state(),
    }, indent=2))


if __name__ == "__main__":
    main()
