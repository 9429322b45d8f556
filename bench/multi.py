"""Multi-robot benchmark: the dissertation's four cases as full demo runs; prints JSON.

Cases 1 and 3 are single robots, 2 and 4 teams (3 and 5 robots) that merge at rendezvous.
Cases ``1-depth`` and ``2-mixed`` put a depth camera on a turning tower in place of a LIDAR
(case 1's robot, to 90 %; case 2's r2 beside r1's LIDAR): the ``mixed`` section reports the
depth robot's error and the team's speed-up over the LIDAR robot alone (case 1).
Reports each case's time to threshold, the team speed-ups (case 1 / case 2, case 3 / case 4),
merge transform errors after joint optimisation against the direct method on the same
sightings, and — with ``--spurious`` — the team cases again with that share of false tag views.

    python bench/multi.py [--cases 1 2 3 4] [--spurious 0.2] [--known-starts] [--thesis-rule]
                          [--seeds 0 1 2 ...] [--single-seed] [--jobs N] [--resume]
                          [--scenarios ambiguous-2 ambiguous-3] [--runs N] [--out DIR]
                          [--detours default|on|off]

Runs with several robots are not exactly repeatable (the server's timing feeds back into the
simulation), so ``--seeds`` runs every requested case once per seed, the single-robot cases
too, and each seed's speed-up divides that seed's single-robot time by its team time
(``--single-seed``: the single robot runs at the first seed only and its time serves every
seed). ``--runs N`` still repeats the team cases N times at each seed. ``--scenarios`` adds
scenarios that ship with the package (``sim/worlds/scenarios.yaml``), such as the
self-similar ``ambiguous-2`` and ``ambiguous-3``, with and without the false views.

Every run's figures are written to ``<out>/runs/<run>.json`` as soon as it ends, so a bench
that is stopped keeps what it did; ``--resume`` skips the runs whose file is there (runs that
failed are tried again). A run that fails (a bad world, a missing report, a crash) is recorded
with its error and the bench goes on. ``--jobs N`` runs up to N demos at once, each in its own
process (each demo is itself several processes: mind the cores).

From each team run's merges the JSON adds the time to the first merge, when each pair of
robots first shared a team and when each pair of teams merged, and the time to one team (the
merge after which one team holds all the run's robots; null if never), each as the median and
the worst over the seeds; merges counted by kind; false merges per variant and in all; the
server's map-matching hypotheses when its report has them; and ``goals_met`` against GOALS.

``teamwork`` judges whether a team pays its way (``bench/support/teamwork.py``): per team case
and seed, its time against its members' alone (the case's single robot: case 1 for 2 and
2-mixed, 3 for 4, ``name-1`` for a packaged ``name-N``), and its longest stretch of flat
coverage while its robots drove (goal: none over 20 s); and, over every run, how the saving
each detour was expected to bring (``detour`` events) agrees with the one measured, for runs
that priced their detours and runs that took them all (``--detours on|off``). The ``mixed``
section adds the depth robot's largest error over the seeds.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
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
from bench.support import teamwork  # noqa: E402

THESIS_SCENARIOS = _HERE.parent.parent / "shared" / "data" / "worlds" / "thesis" / "scenarios.yaml"

GOALS: dict[str, Any] = {
    "speedup_case2": 2.5, "speedup_case4": 3.5, "merge_error_m": 0.05,
    "merge_error_deg": 1.0, "max_position_error_m": {"2": 0.15, "4": 0.40},
    "false_merges": 0}

TEAM_CASES = ("2", "4")
SINGLE_OF = {"2": "1", "4": "3"}

#: mixed sensors in the dissertation's small house: case 1's robot with the depth camera on its
#: tower instead of the LIDAR, and case 2's first two robots with r2's LIDAR so replaced; each
#: with its own coverage goal, and the robot whose error is judged
MIXED_CASES: dict[str, dict[str, Any]] = {
    "1-depth": {"base": "1", "robots": ("r1",), "sensors": {"r1": "depth"}, "coverage": 0.90,
                "judged": "r1", "max_error_m": 0.25},
    "2-mixed": {"base": "2", "robots": ("r1", "r2"), "sensors": {"r2": "depth"},
                "coverage": None, "judged": "r2", "max_error_m": 0.15, "faster_than": "1"},
}
HYPOTHESIS_STATUSES = ("accepted", "refused", "meeting", "confirmed", "refuted", "pending")


# ---------------------------------------------------------------------------------------------
# what to run


@dataclass(frozen=True)
class RunSpec:
    """One demo run of the bench."""

    key: str                 # file name in <out>/runs and the run folder's name
    group: str               # what the run measures: "1", "2", "2-spurious", "ambiguous-2", ...
    case: str                # "1".."4" or a packaged scenario's name
    variant: str             # "plain", "spurious", "known-starts" or "thesis-rule"
    seed: int
    repeat: int = 1          # --runs: the how-many-th run of this group at this seed
    spurious: float = 0.0
    known_starts: bool = False
    coordination: str = "joint"
    packaged: bool = False   # a scenario of the package's scenarios.yaml, not the dissertation's

    def demo_config(self, out: Path, max_sim_time_s: float) -> dict[str, Any]:
        cfg: dict[str, Any] = {
            "seed": self.seed, "out": str(out), "spurious_detections": self.spurious,
            "max_sim_time_s": max_sim_time_s, "known_starts": self.known_starts,
            "coordination": self.coordination, "wall_timeout_s": 5400}
        if self.packaged:
            cfg["scenario"] = self.case
        elif self.case in MIXED_CASES:
            mixed = MIXED_CASES[self.case]
            scenario = f"thesis-case-{mixed['base']}"
            spawn = _thesis_robots(scenario)
            cfg.update(scenario=scenario, scenarios_file=str(THESIS_SCENARIOS),
                       robots={r: spawn[r] for r in mixed["robots"]},
                       sensors=dict(mixed["sensors"]))
            if mixed["coverage"] is not None:
                cfg["coverage"] = mixed["coverage"]
        else:
            cfg.update(scenario=f"thesis-case-{self.case}",
                       scenarios_file=str(THESIS_SCENARIOS))
        return cfg


def _thesis_robots(scenario: str) -> dict[str, list[float]]:
    from sim.config import load_scenario

    case = load_scenario(THESIS_SCENARIOS, scenario)
    return {str(k): [float(x) for x in v] for k, v in dict(case["robots"]).items()}


def plan_runs(cases: list[str], seeds: list[int], spurious: float = 0.0,
              known_starts: bool = False, thesis_rule: bool = False, runs: int = 1,
              single_seed: bool = False, scenarios: Iterable[str] = ()) -> list[RunSpec]:
    """Every run the options ask for, in the order they are run."""
    out: list[RunSpec] = []
    for seed_i, seed in enumerate(seeds):
        for case in cases:
            team = case in TEAM_CASES
            if case in SINGLE_OF.values() and single_seed and seed_i > 0:
                continue
            for k in range(1, (runs if team else 1) + 1):
                tail = f"-run{k}" if k > 1 else ""
                out.append(RunSpec(f"case-{case}-seed{seed}{tail}", case, case, "plain",
                                   seed, k))
            if not team:
                continue
            if spurious > 0:
                out.append(RunSpec(f"case-{case}-spurious-seed{seed}", f"{case}-spurious",
                                   case, "spurious", seed, spurious=spurious))
            if known_starts:
                out.append(RunSpec(f"case-{case}-known-starts-seed{seed}",
                                   f"{case}-known-starts", case, "known-starts", seed,
                                   known_starts=True))
            if thesis_rule:
                out.append(RunSpec(f"case-{case}-thesis-rule-seed{seed}",
                                   f"{case}-thesis-rule", case, "thesis-rule", seed,
                                   coordination="greedy"))
        for name in scenarios:
            out.append(RunSpec(f"{name}-seed{seed}", name, name, "plain", seed, packaged=True))
            if spurious > 0:
                out.append(RunSpec(f"{name}-spurious-seed{seed}", f"{name}-spurious", name,
                                   "spurious", seed, spurious=spurious, packaged=True))
    return out


# ---------------------------------------------------------------------------------------------
# one run


def figures(r: dict[str, Any]) -> dict[str, Any]:
    """The figures the bench keeps of one demo report (``report.json``)."""
    robots = r["robots"]
    merges = r.get("merges", [])
    row: dict[str, Any] = {
        "reached": r["reached"], "threshold": r["threshold"],
        "sim_time_to_threshold_s": r["sim_time_to_threshold_s"],
        "first_team_time_to_threshold_s": r.get("first_team_time_to_threshold_s"),
        "robot_ids": sorted(r.get("robots_spawn") or robots),
        "teams": {k: {"robots": v["robot_ids"], "coverage": v.get("coverage"),
                      "merged_into": v.get("merged_into"),
                      "sim_time_to_threshold_s": v.get("sim_time_to_threshold_s")}
                  for k, v in r["teams"].items()},
        "true_coverage": r["true_coverage"], "phantom_area_m2": r["phantom_area_m2"],
        "max_position_error_m": max((x["max_position_error_m"] or 0.0
                                     for x in robots.values()), default=0.0),
        "max_yaw_error_rad": max((x["max_yaw_error_rad"] or 0.0 for x in robots.values()),
                                 default=0.0),
        "max_position_error_by_robot_m": {k: x["max_position_error_m"]
                                          for k, x in robots.items()},
        # the same where each robot's team map placed it (after its merge), mrslam.report
        "max_team_position_error_by_robot_m": {k: x.get("max_team_position_error_m")
                                               for k, x in robots.items()},
        "collisions": sum(x["collisions"] for x in robots.values()),
        "merges": merges, "false_merges": r.get("false_merges", 0),
        "tag_counters": r.get("tag_counters", {}),
        "wall_time_s": r["wall_time_s"], "end": r["end"],
    }
    if "hypotheses" in r:
        row["hypotheses"] = r["hypotheses"]
        row["map_query_ms_median"] = r.get("map_query_ms_median")
    row["detours"] = teamwork.detour_pairs(r.get("events") or [])
    return row


def run_figures(report: dict[str, Any], out: Path) -> dict[str, Any]:
    """``figures`` of a run's report, and what its folder adds: the team's flat stretches
    (the simulator's truth tells who drove) and whether the server priced its detours."""
    row = figures(report)
    row["flat_coverage"] = teamwork.flat_stretches(
        report, teamwork.distances(out / "sim" / "truth.jsonl"))
    row["detours_enabled"] = _detours_enabled(out)
    return row


def _detours_enabled(out: Path) -> bool | None:
    """``detours.enabled`` as the run's server had it (its config as written), None unknown."""
    import yaml

    try:
        cfg = yaml.safe_load((out / "server" / "server_config.yaml").read_text())
        return bool(cfg["detours"]["enabled"])
    except (OSError, ValueError, KeyError, TypeError, yaml.YAMLError):
        return None


def refresh(done: dict[str, Any]) -> dict[str, Any]:
    """A finished run's figures computed afresh from its folder's report (figures added to
    the bench since it ran); as it was when the report is gone."""
    out = Path(str(done.get("run", "")))
    try:
        report = json.loads((out / "report.json").read_text())
        return {**done, **run_figures(report, out)}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return done


def one(case: str, out: Path, seed: int, spurious: float, max_sim_time_s: float,
        known_starts: bool = False, coordination: str = "joint") -> dict[str, Any]:
    """One dissertation case as a demo run (raises on failure)."""
    spec = RunSpec(out.name, case, case, "plain", seed, spurious=spurious,
                   known_starts=known_starts, coordination=coordination)
    return _demo(spec, out, max_sim_time_s)


def _demo(spec: RunSpec, out: Path, max_sim_time_s: float) -> dict[str, Any]:
    from mrslam.demo import run

    report = run(spec.demo_config(out, max_sim_time_s), progress=False)
    # the report as written to the run folder is what counts; fall back on the one returned
    path = out / "report.json"
    if path.exists():
        try:
            report = json.loads(path.read_text())
        except ValueError as e:
            raise RuntimeError(f"{path}: not valid JSON ({e})") from None
    try:
        return {**run_figures(report, out), "run": str(out)}
    except (KeyError, TypeError, AttributeError) as e:
        raise RuntimeError(f"{path}: the report lacks or mangles {e}") from None


def execute(spec: RunSpec, base: Path, max_sim_time_s: float) -> dict[str, Any]:
    """Run one spec; never raises: a failure comes back as ``status: failed`` with its error.
    Importable by a worker process."""
    head = {"key": spec.key, "group": spec.group, "case": spec.case, "variant": spec.variant,
            "seed": spec.seed, "repeat": spec.repeat, "spurious": spec.spurious}
    out = base / spec.key
    try:
        if not spec.packaged and not THESIS_SCENARIOS.is_file():
            raise FileNotFoundError(f"{THESIS_SCENARIOS}: the dissertation's scenarios are "
                                    "missing (../shared/data)")
        return {**head, "status": "ok", **_demo(spec, out, max_sim_time_s)}
    except Exception as e:  # any failure of one run is that run's result
        return {**head, "status": "failed", "run": str(out),
                "error": f"{type(e).__name__}: {e}",
                "traceback": traceback.format_exc(limit=8)}


def _write_json(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def load_done(path: Path) -> dict[str, Any] | None:
    """A run's file from an earlier bench, if it holds a finished run (else None)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("status") != "ok":
        return None
    return data


#: seconds between the starts of demos run at once (``--jobs``)
STAGGER_S = 20.0


def run_all(specs: list[RunSpec], base: Path, max_sim_time_s: float, jobs: int = 1,
            resume: bool = False,
            runner: Callable[[RunSpec, Path, float], dict[str, Any]] = execute,
            log: Callable[[str], None] = lambda s: print(s, file=sys.stderr)
            ) -> dict[str, dict[str, Any]]:
    """Every spec's result by key, each written to ``<base>/runs/<key>.json`` as it ends."""
    results: dict[str, dict[str, Any]] = {}
    todo: list[RunSpec] = []
    for spec in specs:
        done = load_done(base / "runs" / f"{spec.key}.json") if resume else None
        if done is not None:
            log(f"{spec.key}: done before, kept")
            results[spec.key] = refresh(done)
        else:
            todo.append(spec)
            # an earlier bench's run of this case and seed: its folder starts afresh (a demo
            # refuses a folder that holds a run)
            shutil.rmtree(base / spec.key, ignore_errors=True)

    def finish(spec: RunSpec, res: dict[str, Any]) -> None:
        results[spec.key] = res
        _write_json(base / "runs" / f"{spec.key}.json", res)
        what = (f"failed: {res.get('error')}" if res.get("status") != "ok" else
                f"reached={res.get('reached')} t={res.get('sim_time_to_threshold_s')} "
                f"false_merges={res.get('false_merges')}")
        log(f"{spec.key}: {what}")

    if jobs <= 1:
        for spec in todo:
            log(f"running {spec.key}...")
            finish(spec, runner(spec, base, max_sim_time_s))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            running: dict[Future[dict[str, Any]], RunSpec] = {}
            queue, last = list(todo), -math.inf
            while running or queue:
                # demos started together race for their ports and their agents' first
                # sessions: start them STAGGER_S apart
                if queue and len(running) < jobs and time.monotonic() - last >= STAGGER_S:
                    spec = queue.pop(0)
                    log(f"started {spec.key}")
                    running[pool.submit(runner, spec, base, max_sim_time_s)] = spec
                    last = time.monotonic()
                    continue
                pause = max(0.0, STAGGER_S - (time.monotonic() - last)) \
                    if queue and len(running) < jobs else None
                if not running:
                    time.sleep(pause or 0.0)
                    continue
                done_f, _ = wait(running, timeout=pause, return_when=FIRST_COMPLETED)
                for f in done_f:
                    spec = running.pop(f)
                    try:
                        res = f.result()
                    except Exception as e:  # e.g. a worker that died
                        res = {"key": spec.key, "group": spec.group, "case": spec.case,
                               "variant": spec.variant, "seed": spec.seed,
                               "repeat": spec.repeat, "status": "failed",
                               "error": f"{type(e).__name__}: {e}"}
                    finish(spec, res)
    return {s.key: results[s.key] for s in specs}


# ---------------------------------------------------------------------------------------------
# aggregation: pure functions of the per-run dicts


def ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a and b else None


def stats(values: dict[Any, float | None]) -> dict[str, Any]:
    """Median, min, max (= worst for times) of the measured values; ``missing`` the keys
    without one (a run that failed, or never got there)."""
    got = [float(v) for v in values.values() if v is not None]
    arr = np.asarray(got, dtype=float)
    return {"per_seed": {str(k): v for k, v in values.items()},
            "median": round(float(np.median(arr)), 3) if got else None,
            "min": round(float(arr.min()), 3) if got else None,
            "max": round(float(arr.max()), 3) if got else None,
            "missing": [str(k) for k, v in values.items() if v is None]}


def _live(merges: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The merges that stood (not undone), in time order."""
    return sorted((m for m in merges if not m.get("undone")),
                  key=lambda m: float(m.get("sim_time_s") or 0.0))


def is_false(m: dict[str, Any]) -> bool:
    return bool(m.get("false_merge", m.get("false", False)))


def one_team_time(merges: list[dict[str, Any]], robot_ids: Iterable[str]) -> float | None:
    """Sim time of the merge after which one team holds every robot of the run (a merge's
    ``robots`` are the joined team's); None if that never happened. A single robot is one
    team from the start (0)."""
    everyone = set(robot_ids)
    if len(everyone) <= 1:
        return 0.0
    for m in _live(merges):
        if everyone <= set(m.get("robots", ())):
            return float(m["sim_time_s"])
    return None


def merge_timeline(run: dict[str, Any]) -> dict[str, Any]:
    """One run's merges: time to the first, when each pair of robots first shared a team, when
    each pair of teams merged, the time to one team, counts by kind and the false ones."""
    merges = run.get("merges") or []
    live = _live(merges)
    robots = sorted(run.get("robot_ids") or {r for m in merges for r in m.get("robots", ())})
    together: dict[str, float | None] = {}
    for i, a in enumerate(robots):
        for b in robots[i + 1:]:
            together[f"{a}+{b}"] = next((float(m["sim_time_s"]) for m in live
                                         if {a, b} <= set(m.get("robots", ()))), None)
    teams: dict[str, float] = {}
    for m in live:
        pair = "+".join(sorted((str(m.get("team_id")), str(m.get("joined_team_id")))))
        teams.setdefault(pair, float(m["sim_time_s"]))
    kinds: dict[str, int] = {}
    for m in merges:
        kinds[str(m.get("kind", "tags"))] = kinds.get(str(m.get("kind", "tags")), 0) + 1
    return {"first_merge_s": float(live[0]["sim_time_s"]) if live else None,
            "robots_together_s": together, "team_pairs_s": teams,
            "one_team_s": one_team_time(merges, robots), "merges": len(merges),
            "undone": sum(1 for m in merges if m.get("undone")),
            "kinds": kinds,
            "false_merges": int(run.get("false_merges", sum(is_false(m) for m in merges)))}


def hypotheses_summary(runs: Iterable[dict[str, Any]]) -> dict[str, Any] | None:
    """Counts of the map-matching hypotheses per status over the runs and the largest error of
    the accepted ones; None when no run's report has hypotheses."""
    seen = False
    runs_list = list(runs)
    counts = dict.fromkeys(HYPOTHESIS_STATUSES, 0)
    wrong: dict[str, int] = {}     # hypotheses off the truth (beyond a false merge's bounds)
    err_m: list[float] = []
    err_deg: list[float] = []
    unscored = 0
    for run in runs_list:
        hyps = run.get("hypotheses")
        if not isinstance(hyps, list):
            continue
        seen = True
        for h in hyps:
            if not isinstance(h, dict):
                continue
            status = str(h.get("status"))
            counts[status] = counts.get(status, 0) + 1
            if h.get("wrong"):
                wrong[status] = wrong.get(status, 0) + 1
            if status == "accepted":
                if h.get("error_m") is None and h.get("error_deg") is None:
                    unscored += 1
                if h.get("error_m") is not None:
                    err_m.append(float(h["error_m"]))
                if h.get("error_deg") is not None:
                    err_deg.append(float(h["error_deg"]))
    if not seen:
        return None
    qms = [float(r["map_query_ms_median"]) for r in runs_list
           if isinstance(r.get("map_query_ms_median"), (int, float))]
    return {"counts": counts, "wrong_by_status": wrong,
            "accepted_max_error_m": max(err_m, default=None),
            "accepted_max_error_deg": max(err_deg, default=None),
            "accepted_unscored": unscored,
            # each run's median query time (one submap against the other map), their median
            "query_ms_median": float(np.median(qms)) if qms else None}


def _t(run: dict[str, Any] | None) -> float | None:
    if not run or run.get("status", "ok") != "ok":
        return None
    v = run.get("sim_time_to_threshold_s")
    return float(v) if v is not None else None


def speedups(runs: dict[str, dict[str, Any]], team_case: str, variant: str = "plain"
             ) -> dict[str, Any] | None:
    """Each seed's speed-up of a team case over the single robot (the same seed's single run,
    else the first seed's: --single-seed), with their median, min and max, and the ratio of
    the two cases' median times (``of_medians``); None when the team case did not run.
    Repeats at one seed (--runs) are listed as ``seed#k``."""
    single = SINGLE_OF[team_case]
    singles = {r["seed"]: r for r in runs.values()
               if r.get("case") == single and r.get("variant") == "plain"
               and r.get("repeat", 1) == 1}
    fallback = singles[min(singles)] if singles else None
    per: dict[str, float | None] = {}
    both: list[tuple[float, float]] = []   # (single, team) times where both have one
    for r in sorted((r for r in runs.values()
                     if r.get("case") == team_case and r.get("variant") == variant),
                    key=lambda r: (r["seed"], r.get("repeat", 1))):
        label = str(r["seed"]) + (f"#{r['repeat']}" if r.get("repeat", 1) > 1 else "")
        a, b = _t(singles.get(r["seed"], fallback)), _t(r)
        per[label] = ratio(a, b)
        if a is not None and b is not None:
            both.append((a, b))
    if not per:
        return None
    out = stats(per)
    # also the single robot's median time over the team's median time, on the seeds both
    # reached the threshold (how a speed-up between different seeds is stated)
    out["of_medians"] = (ratio(float(np.median([a for a, _ in both])),
                               float(np.median([b for _, b in both]))) if both else None)
    return out


def _time_stats(values: dict[str, float | None]) -> dict[str, Any]:
    """Median and worst of times over seeds; ``never`` the seeds where it did not happen."""
    s = stats(values)
    return {"median_s": s["median"], "worst_s": s["max"], "per_seed": s["per_seed"],
            "never": s["missing"]}


def _seed_label(r: dict[str, Any]) -> str:
    return str(r["seed"]) + (f"#{r['repeat']}" if r.get("repeat", 1) > 1 else "")


def merge_report(runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per group (case and variant) of multi-robot runs: merge times over the seeds (median,
    worst), merges by kind, false merges, hypotheses; and the false merges per variant and
    in all."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in runs.values():
        if r.get("status", "ok") == "ok" and len(r.get("robot_ids") or ()) > 1:
            groups.setdefault(str(r["group"]), []).append(r)
    out: dict[str, Any] = {}
    by_variant: dict[str, int] = {}
    for group, rs in sorted(groups.items()):
        rs.sort(key=lambda r: (r["seed"], r.get("repeat", 1)))
        lines = {_seed_label(r): merge_timeline(r) for r in rs}
        pairs = sorted({p for ln in lines.values() for p in ln["robots_together_s"]})
        team_pairs = sorted({p for ln in lines.values() for p in ln["team_pairs_s"]})
        kinds: dict[str, int] = {}
        for ln in lines.values():
            for k, n in ln["kinds"].items():
                kinds[k] = kinds.get(k, 0) + n
        false = sum(ln["false_merges"] for ln in lines.values())
        variant = str(rs[0].get("variant", "plain"))
        by_variant[variant] = by_variant.get(variant, 0) + false
        out[group] = {
            "runs": len(rs),
            "reached": sum(bool(r.get("reached")) for r in rs),
            "time_to_threshold": _time_stats({s: _t(r) for s, r in
                                              zip(lines, rs, strict=True)}),
            "first_merge": _time_stats({s: ln["first_merge_s"] for s, ln in lines.items()}),
            "one_team": _time_stats({s: ln["one_team_s"] for s, ln in lines.items()}),
            "robots_together": {p: _time_stats({s: ln["robots_together_s"].get(p)
                                                for s, ln in lines.items()}) for p in pairs},
            "team_pairs": {p: _time_stats({s: ln["team_pairs_s"].get(p)
                                           for s, ln in lines.items()}) for p in team_pairs},
            "merges": sum(ln["merges"] for ln in lines.values()),
            "undone": sum(ln["undone"] for ln in lines.values()),
            "merge_kinds": kinds, "false_merges": false,
            "false_merges_per_seed": {s: ln["false_merges"] for s, ln in lines.items()},
            "hypotheses": hypotheses_summary(rs),
        }
    return {"groups": out, "false_merges_by_variant": by_variant,
            "false_merges_total": sum(by_variant.values())}


def goals_met(res: dict[str, Any], goals: dict[str, Any] = GOALS) -> dict[str, Any]:
    """Each goal: the measured value, the goal, and whether it is met (None: not measured).
    A speed-up goal counts the median over the seeds and is not met while a seed lacks its
    figure (a run failed or did not reach the threshold)."""
    out: dict[str, Any] = {}
    for case in TEAM_CASES:
        sp = (res.get("speedup") or {}).get(case)
        key = f"speedup_case{case}"
        if not sp or sp["median"] is None:
            out[key] = {"value": None, "goal": goals[key], "met": None}
            continue
        out[key] = {"value": sp["median"], "goal": goals[key], "per_seed": sp["per_seed"],
                    "of_medians": sp.get("of_medians"),
                    "met": sp["median"] >= goals[key] and not sp["missing"]}
        if sp["missing"]:
            out[key]["note"] = f"no figure for seed(s) {', '.join(sp['missing'])}"
    mr = res.get("merge_report") or {}
    n_false = mr.get("false_merges_total")
    out["false_merges"] = {"value": n_false, "goal": goals["false_merges"],
                           "by_variant": mr.get("false_merges_by_variant", {}),
                           "met": None if n_false is None or not mr.get("groups")
                           else n_false <= goals["false_merges"]}
    for name, goal in (("merge_error_joint_max_m", goals["merge_error_m"]),
                       ("merge_error_joint_max_deg", goals["merge_error_deg"])):
        v = res.get(name)
        out[name] = {"value": v, "goal": goal, "met": None if v is None else v <= goal}
    for case, goal in goals["max_position_error_m"].items():
        errs = [r["max_position_error_m"] for r in (res.get("runs") or {}).values()
                if r.get("case") == case and r.get("variant") == "plain"
                and r.get("status", "ok") == "ok"]
        v = max(errs) if errs else None
        out[f"max_position_error_case{case}_m"] = {
            "value": v, "goal": goal, "met": None if v is None else v <= goal}
    return out


def legacy_cases(runs: dict[str, dict[str, Any]], first_seed: int) -> dict[str, Any]:
    """The first seed's runs under the names the bench always used ("1", "2", "2#2",
    "2-spurious", "2-known-starts", ...); a failed run is listed with its error."""
    out: dict[str, Any] = {}
    for r in runs.values():
        if r.get("seed") != first_seed or r.get("case") not in ("1", "2", "3", "4"):
            continue
        name = str(r["group"]) + (f"#{r['repeat']}" if r.get("repeat", 1) > 1 else "")
        out[name] = r
    return out


def summarise(runs: dict[str, dict[str, Any]], seeds: list[int],
              scenarios: Iterable[str] = ()) -> dict[str, Any]:
    """The bench's JSON document from the runs' dicts."""
    c = legacy_cases(runs, seeds[0])
    res: dict[str, Any] = {"cases": c, "goals": GOALS, "seeds": seeds}

    def t(k: str) -> float | None:
        return _t(c.get(k))

    def first(k: str) -> float | None:
        r = c.get(k)
        return r.get("first_team_time_to_threshold_s") if r and r.get("status") == "ok" \
            else None

    # all final teams at the threshold (the goal's measure), and the first team alone
    res["speedup_case2"] = ratio(t("1"), t("2"))
    res["speedup_case4"] = ratio(t("3"), t("4"))
    res["speedup_case2_first_team"] = ratio(t("1"), first("2"))
    res["speedup_case4_first_team"] = ratio(t("3"), first("4"))
    for k, single in SINGLE_OF.items():
        rs = [ratio(t(single), t(key)) for key in c if key.split("#")[0] == k]
        if len(rs) > 1 and None not in rs:
            res[f"speedup_case{k}_runs"] = rs
            res[f"speedup_case{k}_median"] = float(np.median(np.asarray(rs, dtype=float)))
    for k, single in SINGLE_OF.items():
        if f"{k}-known-starts" in c:
            res[f"speedup_case{k}_known_starts"] = ratio(t(single), t(f"{k}-known-starts"))
        if f"{k}-thesis-rule" in c:
            res[f"speedup_case{k}_thesis_rule"] = ratio(t(single), t(f"{k}-thesis-rule"))
    # every seed's speed-up, per variant
    res["speedup"] = {}
    for k in TEAM_CASES:
        for variant in ("plain", "spurious", "known-starts", "thesis-rule"):
            sp = speedups(runs, k, variant)
            if sp is not None:
                res["speedup"][k if variant == "plain" else f"{k}-{variant}"] = sp
    ok = [r for r in runs.values() if r.get("status", "ok") == "ok"]
    merges = [m for r in ok if r.get("case") in TEAM_CASES and r.get("variant") == "plain"
              for m in r.get("merges", [])
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
    res["false_merges"] = {k: v.get("false_merges") for k, v in c.items()}
    res["merge_report"] = merge_report(runs)
    res["scenarios"] = {}
    for name in scenarios:
        for r in sorted((r for r in runs.values() if r.get("case") == name),
                        key=lambda r: (r["group"], r["seed"])):
            res["scenarios"].setdefault(str(r["group"]), {})[str(r["seed"])] = (
                {"status": "failed", "error": r.get("error")} if r.get("status") != "ok" else
                {"reached": r.get("reached"),
                 "sim_time_to_threshold_s": r.get("sim_time_to_threshold_s"),
                 "false_merges": r.get("false_merges"),
                 "merges": merge_timeline(r)["merges"],
                 "merge_kinds": merge_timeline(r)["kinds"],
                 "one_team_s": merge_timeline(r)["one_team_s"]})
    res["mixed"] = mixed_report(runs)
    res["teamwork"] = teamwork_report(runs)
    res["hypotheses"] = hypotheses_summary(ok)
    res["failed_runs"] = {k: r.get("error") for k, r in runs.items()
                          if r.get("status", "ok") != "ok"}
    res["runs"] = {k: {x: r.get(x) for x in ("group", "seed", "repeat", "status", "reached",
                                              "sim_time_to_threshold_s", "false_merges",
                                              "error", "run")}
                   for k, r in runs.items()}
    res["goals_met"] = goals_met({**res, "runs": runs})
    return res


#: a team case's single-robot case: its first robot alone, at the same spawn
TEAM_ALONE = {"2": "1", "4": "3", "2-mixed": "1"}
#: the issue's goals for any team: no slower than its fastest member alone, and no stretch
#: longer than this of flat coverage while its robots drive [s]
FLAT_GOAL_S = 20.0


def alone_case(case: str, cases: Iterable[str]) -> str | None:
    """The single-robot case a team case is measured against: the dissertation's, or a
    packaged scenario ``name-N``'s ``name-1``."""
    if case in TEAM_ALONE:
        return TEAM_ALONE[case]
    head, _, n = case.rpartition("-")
    if n.isdigit() and int(n) > 1 and f"{head}-1" in cases:
        return f"{head}-1"
    return None


def teamwork_report(runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per team group and seed: the team's time against its members' alone (those run: the
    case's single robot), its longest flat coverage while its robots drove; over every run,
    how the detours' estimated savings agree with the measured ones (separately for runs
    that priced their detours and runs that took them all)."""
    ok = [r for r in runs.values() if r.get("status", "ok") == "ok"]
    cases = {str(r.get("case")) for r in ok}
    groups: dict[str, Any] = {}
    for r in sorted(ok, key=lambda r: (str(r["group"]), r["seed"], r.get("repeat", 1))):
        single = alone_case(str(r["case"]), cases)
        if single is None or len(r.get("robot_ids") or ()) < 2:
            continue
        alone = {x["robot_ids"][0]: _t(x) for x in ok if x.get("case") == single
                 and x.get("seed") == r["seed"] and x.get("variant") == "plain"
                 and x.get("robot_ids")}
        flat = r.get("flat_coverage") or {}
        g = groups.setdefault(str(r["group"]), {"alone_case": single, "seeds": {}})
        g["seeds"][_seed_label(r)] = {
            **teamwork.team_vs_alone(_t(r), alone),
            "flat_longest_s": flat.get("longest_s"), "flat": {
                k: flat.get(k) for k in ("team", "from_s", "to_s", "driven_m")},
            "collisions": r.get("collisions"), "detours_enabled": r.get("detours_enabled")}
    for g in groups.values():
        rows = g["seeds"].values()
        sp = [v["speedup"] for v in rows if v["speedup"] is not None]
        flats = [v["flat_longest_s"] for v in rows if v["flat_longest_s"] is not None]
        g["speedup_median"] = round(float(np.median(sp)), 3) if sp else None
        g["never_slower"] = all(v["no_slower"] for v in rows) if sp else None
        g["flat_longest_s"] = max(flats) if flats else None
        g["flat_goal_met"] = all(f <= FLAT_GOAL_S for f in flats) if flats else None
    corr: dict[str, Any] = {}
    for label, want in (("priced", True), ("all_taken", False)):
        pairs = [p for r in ok if r.get("detours_enabled") is want
                 for p in r.get("detours") or []]
        if pairs:
            corr[label] = teamwork.correlation(pairs)
    return {"groups": groups, "flat_goal_s": FLAT_GOAL_S, "detour_estimates": corr}


def mixed_report(runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per mixed case and seed: reached, time, the judged (depth) robot's largest position
    error (the larger of its own frame's and its team map's), collisions, false merges, and
    the speed-up over the LIDAR robot alone (the same seed's case 1, else the first seed's);
    and whether the case's goals hold at every seed."""
    out: dict[str, Any] = {}
    for name, mixed in MIXED_CASES.items():
        rows: dict[str, Any] = {}
        for r in sorted((r for r in runs.values() if r.get("case") == name),
                        key=lambda r: r["seed"]):
            if r.get("status", "ok") != "ok":
                rows[str(r["seed"])] = {"status": "failed", "error": r.get("error")}
                continue
            own = (r.get("max_position_error_by_robot_m") or {}).get(mixed["judged"])
            in_team = (r.get("max_team_position_error_by_robot_m") or {}).get(mixed["judged"])
            # judged by the larger: in its own map frame (the start as origin), and where the
            # team's map put it after the merge (the LIDAR robot's frame)
            err = None if own is None else max(own, in_team or 0.0)
            row: dict[str, Any] = {
                "reached": r.get("reached"), "threshold": r.get("threshold"),
                "sim_time_to_threshold_s": r.get("sim_time_to_threshold_s"),
                f"max_position_error_{mixed['judged']}_m": err,
                f"max_own_frame_error_{mixed['judged']}_m": own,
                f"max_team_frame_error_{mixed['judged']}_m": in_team,
                "max_position_error_m": r.get("max_position_error_m"),
                "collisions": r.get("collisions"), "false_merges": r.get("false_merges"),
                "merges": len(_live(r.get("merges", [])))}
            if "faster_than" in mixed:
                singles = [x for x in runs.values() if x.get("case") == mixed["faster_than"]
                           and x.get("variant") == "plain" and x.get("status", "ok") == "ok"]
                same = [x for x in singles if x.get("seed") == r["seed"]] or singles[:1]
                t1 = _t(same[0]) if same else None
                row["lidar_alone_s"] = t1
                row["speedup_over_lidar_alone"] = ratio(t1, _t(r))
            row["goals_met"] = bool(
                r.get("reached") and err is not None and err <= mixed["max_error_m"]
                and not r.get("collisions") and not r.get("false_merges")
                and ("faster_than" not in mixed or (row.get("speedup_over_lidar_alone") or 0) > 1))
            rows[str(r["seed"])] = row
        if rows:
            errs = [v.get(f"max_position_error_{mixed['judged']}_m") for v in rows.values()]
            got = [e for e in errs if e is not None]
            out[name] = {"goal_max_error_m": mixed["max_error_m"],
                         "max_error_over_seeds_m": max(got) if got else None,
                         "goal_coverage": mixed["coverage"], "seeds": rows,
                         "all_goals_met": all(v.get("goals_met") for v in rows.values())}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=["1", "2", "3", "4"],
                    choices=["1", "2", "3", "4", *MIXED_CASES],
                    help="the dissertation's cases, and mixed-sensor ones: 1-depth (case 1's "
                    "robot with a depth camera on a tower), 2-mixed (case 2's r1 with its "
                    "LIDAR, r2 with the depth camera)")
    ap.add_argument("--spurious", type=float, default=0.2,
                    help="also run the team cases and scenarios with this share of false "
                    "views (0: skip)")
    ap.add_argument("--known-starts", action="store_true",
                    help="also run the team cases with the start poses given to the server "
                    "(one team from the start: what coordination alone gains)")
    ap.add_argument("--thesis-rule", action="store_true",
                    help="also run the team cases with the dissertation's target rule "
                    "(--coordination greedy) instead of the joint assignment")
    ap.add_argument("--seed", type=int, default=0, help="the one seed, without --seeds")
    ap.add_argument("--seeds", type=int, nargs="+", default=None,
                    help="run every case once per seed (the single-robot cases too)")
    ap.add_argument("--single-seed", action="store_true",
                    help="run the single-robot cases (1, 3) at the first seed only and use "
                    "their time for every seed's speed-up")
    ap.add_argument("--scenarios", nargs="+", default=[],
                    help="also run these scenarios of the package's sim/worlds/scenarios.yaml "
                    "(e.g. ambiguous-2 ambiguous-3), with and without --spurious")
    ap.add_argument("--runs", type=int, default=1,
                    help="run each team case (2, 4) this many times per seed")
    ap.add_argument("--jobs", type=int, default=1, help="demo runs at once (processes)")
    ap.add_argument("--resume", action="store_true",
                    help="skip the runs whose JSON is already in <out>/runs")
    ap.add_argument("--detours", choices=["default", "on", "off"], default="default",
                    help="the server's detours.enabled for every run (on: each detour priced "
                    "and taken only when worth it; off: every detour taken, still priced); "
                    "default: the server's default")
    ap.add_argument("--max-sim-time", type=float, default=7200.0)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.runs < 1 or a.jobs < 1:
        ap.error("--runs and --jobs must be at least 1")
    seeds = list(dict.fromkeys(a.seeds if a.seeds else [a.seed]))
    if any(s < 0 for s in seeds):
        ap.error("seeds must be ≥ 0")
    if a.scenarios:
        from sim.config import DEFAULT_SCENARIOS, load_scenario
        from sim.errors import SimError

        for name in a.scenarios:
            try:
                load_scenario(DEFAULT_SCENARIOS, name)
            except SimError as e:
                ap.error(str(e))
    base = a.out or Path(tempfile.mkdtemp(prefix="mrslam-multi-"))
    if a.detours != "default":   # the servers the demos start read it from their environment
        os.environ["MRSLAM_DETOURS__ENABLED"] = "true" if a.detours == "on" else "false"
    specs = plan_runs(a.cases, seeds, a.spurious, a.known_starts, a.thesis_rule, a.runs,
                      a.single_seed, a.scenarios)
    print(f"{len(specs)} run(s) into {base}", file=sys.stderr)
    runs = run_all(specs, base, a.max_sim_time, a.jobs, a.resume)
    res = summarise(runs, seeds, a.scenarios)
    res["out"] = str(base)
    res["detours"] = a.detours
    _write_json(base / "summary.json", res)
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
