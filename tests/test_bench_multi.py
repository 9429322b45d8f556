"""bench/multi.py's bookkeeping without the simulator: which runs the options ask for, the
per-seed speed-ups, merge times (median, worst, time to one team), false merges, hypotheses,
goals, and the run files that let a stopped bench resume. The runs are synthetic dicts shaped
as the bench keeps them from each run's ``report.json``."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_multi", ROOT / "bench" / "multi.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_multi"] = mod   # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


multi = _load()


def merge(t: float, team: str, joined: str, robots: list[str], kind: str = "tags",
          false: bool = False, undone: bool = False) -> dict[str, Any]:
    return {"sim_time_s": t, "team_id": team, "joined_team_id": joined, "robots": robots,
            "kind": kind, "false_merge": false, "undone": undone}


def run(case: str, seed: int, t: float | None, merges: list[dict[str, Any]] | None = None,
        variant: str = "plain", robots: int = 3, repeat: int = 1,
        **extra: Any) -> dict[str, Any]:
    group = case if variant == "plain" else f"{case}-{variant}"
    merges = merges or []
    return {"key": f"{group}-seed{seed}" + (f"-run{repeat}" if repeat > 1 else ""),
            "group": group, "case": case, "variant": variant, "seed": seed,
            "repeat": repeat, "status": "ok", "reached": t is not None,
            "sim_time_to_threshold_s": t, "first_team_time_to_threshold_s": t,
            "robot_ids": [f"r{i}" for i in range(1, robots + 1)], "merges": merges,
            "false_merges": sum(bool(m.get("false_merge")) for m in merges),
            "max_position_error_m": 0.1, **extra}


def keyed(*runs: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {r["key"]: r for r in runs}


def test_the_plan_runs_every_case_once_per_seed_and_the_single_robot_once_if_asked() -> None:
    specs = multi.plan_runs(["1", "2"], [0, 1, 2], spurious=0.2, scenarios=["ambiguous-2"])
    keys = [s.key for s in specs]
    assert len(keys) == len(set(keys))
    for seed in (0, 1, 2):
        assert {f"case-1-seed{seed}", f"case-2-seed{seed}", f"case-2-spurious-seed{seed}",
                f"ambiguous-2-seed{seed}", f"ambiguous-2-spurious-seed{seed}"} <= set(keys)
    assert "case-1-spurious-seed0" not in keys   # a single robot has no one to merge with
    amb = next(s for s in specs if s.key == "ambiguous-2-spurious-seed1")
    assert amb.packaged and amb.spurious == 0.2
    assert amb.demo_config(Path("/x"), 60.0) == {
        "seed": 1, "out": "/x", "spurious_detections": 0.2, "max_sim_time_s": 60.0,
        "known_starts": False, "coordination": "joint", "wall_timeout_s": 5400,
        "scenario": "ambiguous-2"}
    thesis = next(s for s in specs if s.key == "case-2-seed2").demo_config(Path("/x"), 60.0)
    assert thesis["scenario"] == "thesis-case-2" and "scenarios_file" in thesis
    single = [s.key for s in multi.plan_runs(["1", "2"], [0, 1, 2], single_seed=True)]
    assert [k for k in single if k.startswith("case-1")] == ["case-1-seed0"]
    repeats = [s.key for s in multi.plan_runs(["2"], [5], runs=3)]
    assert repeats == ["case-2-seed5", "case-2-seed5-run2", "case-2-seed5-run3"]


def test_each_seeds_speed_up_uses_that_seeds_single_robot() -> None:
    runs = keyed(run("3", 0, 4000.0, robots=1), run("3", 1, 3000.0, robots=1),
                 run("3", 2, 5000.0, robots=1),
                 run("4", 0, 1000.0, robots=5), run("4", 1, 1000.0, robots=5),
                 run("4", 2, None, robots=5))
    sp = multi.speedups(runs, "4")
    assert sp["per_seed"] == {"0": 4.0, "1": 3.0, "2": None}
    assert sp["median"] == 3.5 and sp["min"] == 3.0 and sp["max"] == 4.0
    assert sp["missing"] == ["2"]
    assert sp["of_medians"] == 3.5                    # 3,500 s over 1,000 s (seeds 0 and 1)
    # the median of the seeds' ratios and the ratio of the medians differ in general
    uneven = keyed(run("3", 0, 4000.0, robots=1), run("3", 1, 3000.0, robots=1),
                   run("4", 0, 1000.0, robots=5), run("4", 1, 1500.0, robots=5))
    sp = multi.speedups(uneven, "4")
    assert sp["median"] == 3.0 and sp["of_medians"] == 2.8
    # --single-seed: the first seed's single robot serves every seed
    only_first = keyed(run("3", 0, 4000.0, robots=1), run("4", 0, 800.0, robots=5),
                       run("4", 1, 2000.0, robots=5))
    assert multi.speedups(only_first, "4")["per_seed"] == {"0": 5.0, "1": 2.0}
    # a seed whose single robot failed has no figure (not the first seed's)
    failed = {**run("3", 1, 3000.0, robots=1), "status": "failed"}
    mixed = keyed(run("3", 0, 4000.0, robots=1), failed, run("4", 1, 1000.0, robots=5))
    assert multi.speedups(mixed, "4")["per_seed"] == {"1": None}


def test_one_team_is_the_merge_that_holds_every_robot_and_undone_merges_do_not_count() -> None:
    robots = ["r1", "r2", "r3"]
    ms = [merge(10.0, "team-r1", "team-r2", ["r1", "r2"]),
          merge(30.0, "team-r1", "team-r3", robots, undone=True),
          merge(50.0, "team-r3", "team-r1", robots)]
    assert multi.one_team_time(ms, robots) == 50.0
    assert multi.one_team_time(ms[:2], robots) is None
    assert multi.one_team_time([], ["r1"]) == 0.0
    line = multi.merge_timeline(run("2", 0, 100.0, ms))
    assert line["first_merge_s"] == 10.0 and line["one_team_s"] == 50.0
    assert line["robots_together_s"] == {"r1+r2": 10.0, "r1+r3": 50.0, "r2+r3": 50.0}
    assert line["team_pairs_s"] == {"team-r1+team-r2": 10.0, "team-r1+team-r3": 50.0}
    assert line["kinds"] == {"tags": 3} and line["undone"] == 1


def test_merge_times_median_and_worst_over_seeds_and_false_merges_per_variant() -> None:
    r = ["r1", "r2", "r3"]
    runs = keyed(
        run("2", 0, 300.0, [merge(20.0, "team-r1", "team-r2", ["r1", "r2"]),
                             merge(80.0, "team-r1", "team-r3", r, kind="map")]),
        run("2", 1, 400.0, [merge(40.0, "team-r2", "team-r3", ["r2", "r3"]),
                             merge(200.0, "team-r2", "team-r1", r)]),
        run("2", 2, None, [merge(60.0, "team-r1", "team-r2", ["r1", "r2"], kind="meeting")]),
        run("2", 0, 350.0, [merge(15.0, "team-r1", "team-r2", ["r1", "r3"], false=True)],
            variant="spurious"),
        run("ambiguous-2", 0, 500.0, [merge(99.0, "team-r1", "team-r2", ["r1", "r2"],
                                            kind="map", false=True)], robots=2),
        run("1", 0, 900.0, robots=1))
    rep = multi.merge_report(runs)
    g = rep["groups"]["2"]
    assert g["runs"] == 3 and g["reached"] == 2
    assert g["first_merge"]["median_s"] == 40.0 and g["first_merge"]["worst_s"] == 60.0
    assert g["one_team"]["per_seed"] == {"0": 80.0, "1": 200.0, "2": None}
    assert g["one_team"]["median_s"] == 140.0 and g["one_team"]["worst_s"] == 200.0
    assert g["one_team"]["never"] == ["2"]
    assert g["robots_together"]["r1+r2"]["per_seed"] == {"0": 20.0, "1": 200.0, "2": 60.0}
    assert g["robots_together"]["r1+r2"]["worst_s"] == 200.0
    assert g["merge_kinds"] == {"tags": 3, "map": 1, "meeting": 1}
    assert g["false_merges"] == 0 and g["time_to_threshold"]["worst_s"] == 400.0
    assert "1" not in rep["groups"]              # a single robot has no merges to time
    assert rep["false_merges_by_variant"] == {"plain": 1, "spurious": 1}
    assert rep["false_merges_total"] == 2
    assert rep["groups"]["ambiguous-2"]["false_merges_per_seed"] == {"0": 1}


def test_hypotheses_are_counted_when_the_report_has_them_and_absent_ones_are_fine() -> None:
    assert multi.hypotheses_summary([run("2", 0, 1.0)]) is None
    hyps = [{"status": "accepted", "support": 5, "error_m": 0.03, "error_deg": 0.5,
             "teams": ["a", "b"]},
            {"status": "accepted", "support": 9, "error_m": 0.2, "error_deg": None,
             "teams": ["a", "c"]},
            {"status": "refuted", "support": 1, "error_m": 7.0, "error_deg": 180.0,
             "teams": ["a", "b"]},
            {"status": "pending", "support": 2, "error_m": None, "error_deg": None,
             "teams": ["b", "c"]}]
    s = multi.hypotheses_summary([run("2", 0, 1.0, hypotheses=hyps), run("2", 1, 1.0),
                                  run("2", 2, 1.0, hypotheses=[])])
    assert s["counts"] == {"accepted": 2, "refused": 0, "meeting": 0, "confirmed": 0,
                           "refuted": 1, "pending": 1}
    assert s["accepted_max_error_m"] == 0.2 and s["accepted_max_error_deg"] == 0.5


def test_the_summary_keeps_the_old_keys_and_checks_the_goals() -> None:
    r = ["r1", "r2", "r3"]
    runs = keyed(run("1", 0, 1000.0, robots=1), run("1", 1, 1200.0, robots=1),
                 run("2", 0, 500.0, [merge(10.0, "team-r1", "team-r2", r)]),
                 run("2", 1, 400.0, [merge(30.0, "team-r1", "team-r2", r)]),
                 run("2", 0, 450.0, variant="spurious"),
                 {"key": "case-2-spurious-seed1", "group": "2-spurious", "case": "2",
                  "variant": "spurious", "seed": 1, "repeat": 1, "status": "failed",
                  "error": "RuntimeError: no report"})
    res = multi.summarise(runs, [0, 1])
    assert res["speedup_case2"] == 2.0      # the first seed, as before
    assert set(res["cases"]) == {"1", "2", "2-spurious"}
    assert res["speedup"]["2"]["per_seed"] == {"0": 2.0, "1": 3.0}
    assert res["speedup"]["2"]["median"] == 2.5
    assert res["speedup"]["2-spurious"]["missing"] == ["1"]
    assert res["false_merges"] == {"1": 0, "2": 0, "2-spurious": 0}
    assert res["failed_runs"] == {"case-2-spurious-seed1": "RuntimeError: no report"}
    goals = res["goals_met"]
    assert goals["speedup_case2"]["met"] is True and goals["speedup_case2"]["value"] == 2.5
    assert goals["speedup_case4"]["met"] is None      # not run
    assert goals["false_merges"]["met"] is True
    json.dumps(res)   # one JSON document
    slow = dict(runs, **keyed(run("2", 1, 1200.0)))
    assert multi.summarise(slow, [0, 1])["goals_met"]["speedup_case2"]["met"] is False
    bad = dict(runs, **keyed(run("2", 1, 400.0, [merge(30.0, "t1", "t2", r, false=True)])))
    assert multi.summarise(bad, [0, 1])["goals_met"]["false_merges"]["met"] is False


def test_runs_are_written_as_they_end_a_failure_does_not_stop_the_bench_and_resume_skips(
        tmp_path: Path) -> None:
    specs = multi.plan_runs(["1", "2"], [0, 1], spurious=0.0)
    calls: list[str] = []

    def runner(spec: Any, base: Path, max_s: float) -> dict[str, Any]:
        calls.append(spec.key)
        if spec.key == "case-2-seed1":
            return {"key": spec.key, "group": spec.group, "case": spec.case,
                    "variant": spec.variant, "seed": spec.seed, "repeat": 1,
                    "status": "failed", "error": "WorldError: broken"}
        # every earlier run's file is already on disk when the next one starts
        assert all((base / "runs" / f"{k}.json").is_file() for k in calls[:-1])
        return run(spec.case, spec.seed, 100.0, robots=1 if spec.case == "1" else 3)

    got = multi.run_all(specs, tmp_path, 60.0, runner=runner, log=lambda s: None)
    assert list(got) == [s.key for s in specs] and len(calls) == 4
    assert got["case-2-seed1"]["status"] == "failed"
    assert json.loads((tmp_path / "runs" / "case-1-seed1.json").read_text())["seed"] == 1
    (tmp_path / "runs" / "case-1-seed0.json").write_text("{not json")
    for key in ("case-1-seed0", "case-2-seed0"):   # the folders of earlier runs
        (tmp_path / key / "server" / "state").mkdir(parents=True)
        (tmp_path / key / "report.json").write_text("{}")
    calls.clear()
    again = multi.run_all(specs, tmp_path, 60.0, resume=True, runner=runner, log=lambda s: None)
    # kept the finished runs; ran again the failed one and the one whose file is broken
    assert sorted(calls) == ["case-1-seed0", "case-2-seed1"]
    assert again["case-2-seed0"]["status"] == "ok"
    # a run done again starts in an empty folder (a demo refuses one that holds a run); a
    # run kept keeps its folder
    assert not (tmp_path / "case-1-seed0").exists()
    assert (tmp_path / "case-2-seed0" / "report.json").is_file()


def test_a_run_that_raises_is_recorded_as_failed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    spec = multi.plan_runs([], [3], scenarios=["ambiguous-2"])[0]

    def broken(*a: Any, **k: Any) -> dict[str, Any]:
        raise RuntimeError("the server did not come up")

    monkeypatch.setattr(multi, "_demo", broken)
    res = multi.execute(spec, tmp_path, 10.0)
    assert res["status"] == "failed" and "did not come up" in res["error"]
    assert res["seed"] == 3 and res["group"] == "ambiguous-2"


def test_a_report_that_lacks_figures_or_is_not_json_is_a_failed_run(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import mrslam.demo

    spec = multi.plan_runs([], [0], scenarios=["ambiguous-3"])[0]
    monkeypatch.setattr(mrslam.demo, "run", lambda cfg, progress=True: {"reached": True})
    res = multi.execute(spec, tmp_path, 10.0)
    assert res["status"] == "failed" and "lacks" in res["error"] and "robots" in res["error"]
    (tmp_path / spec.key).mkdir()
    (tmp_path / spec.key / "report.json").write_text("{")
    res = multi.execute(spec, tmp_path, 10.0)
    assert res["status"] == "failed" and "not valid JSON" in res["error"]


def test_mixed_cases_put_the_depth_camera_on_the_named_robot_and_judge_it() -> None:
    specs = multi.plan_runs(["1", "1-depth", "2-mixed"], [0, 1], spurious=0.2,
                            single_seed=True)
    keys = [s.key for s in specs]
    assert keys == ["case-1-seed0", "case-1-depth-seed0", "case-2-mixed-seed0",
                    "case-1-depth-seed1", "case-2-mixed-seed1"]   # no false-view variants
    cfg = next(s for s in specs if s.key == "case-2-mixed-seed1").demo_config(Path("/x"), 60.0)
    assert cfg["scenario"] == "thesis-case-2" and cfg["sensors"] == {"r2": "depth"}
    assert set(cfg["robots"]) == {"r1", "r2"} and "coverage" not in cfg
    alone = next(s for s in specs if s.key == "case-1-depth-seed0").demo_config(Path("/x"), 9.0)
    assert alone["sensors"] == {"r1": "depth"} and alone["coverage"] == 0.90
    runs = keyed(run("1", 0, 200.0, robots=1),
                 run("1-depth", 0, 700.0, robots=1, collisions=0,
                     max_position_error_by_robot_m={"r1": 0.2}),
                 run("2-mixed", 0, 160.0, robots=2, collisions=0,
                     max_position_error_by_robot_m={"r1": 0.05, "r2": 0.12}),
                 run("2-mixed", 1, 250.0, robots=2, collisions=1,
                     max_position_error_by_robot_m={"r1": 0.05, "r2": 0.3}))
    rep = multi.mixed_report(runs)
    s0, s1 = rep["2-mixed"]["seeds"]["0"], rep["2-mixed"]["seeds"]["1"]
    assert s0["speedup_over_lidar_alone"] == 1.25 and s0["goals_met"]
    assert s0["max_position_error_r2_m"] == 0.12
    # slower than the LIDAR alone (seed 1 has no case 1: the first seed's serves), off, and
    # a collision
    assert s1["lidar_alone_s"] == 200.0 and s1["speedup_over_lidar_alone"] == 0.8
    assert not s1["goals_met"] and not rep["2-mixed"]["all_goals_met"]
    assert rep["1-depth"]["seeds"]["0"]["goals_met"] and rep["1-depth"]["all_goals_met"]


# -- teamwork: flat coverage, detours' estimates, the team against its members alone ---------

def _team(history: list[tuple[float, float]], robots: list[str], end: float | None = None
          ) -> dict[str, Any]:
    return {"robot_ids": robots, "coverage_history": [list(h) for h in history],
            "sim_time_to_threshold_s": end}


def test_flat_coverage_counts_only_while_the_teams_robots_drive() -> None:
    import numpy as np

    from bench.support import teamwork

    # team-r1: grows to 10 s, flat 10–40 s (r1 drives), grows again; team-r2: flat 0–30 s
    # but r2 stands still all along
    h1 = [(t, min(t, 10) * 0.05 + max(0, t - 40) * 0.05) for t in range(0, 51)]
    h2 = [(t, 0.5) for t in range(0, 31)]
    report = {"area_m2": 100.0, "merges": [],
              "teams": {"team-r1": _team(h1, ["r1"], end=50.0), "team-r2": _team(h2, ["r2"])}}
    t = np.arange(0.0, 51.0)
    truth = {"r1": (t, 0.3 * t), "r2": (t, np.zeros_like(t))}
    flat = teamwork.flat_stretches(report, truth)
    assert flat["team"] == "team-r1"
    assert flat["longest_s"] == 30.0 and (flat["from_s"], flat["to_s"]) == (10.0, 40.0)
    assert flat["driven_m"] == 9.0
    assert flat["teams"]["team-r2"]["longest_s"] == 0.0
    # r2, merged into team-r1 at 5 s, drives for the team too: both robots' distances count
    report["merges"] = [merge(5.0, "team-r1", "team-r2", ["r1", "r2"])]
    truth["r2"] = (t, 0.3 * t)
    assert teamwork.flat_stretches(report, truth)["driven_m"] == 18.0


def test_detour_estimates_paired_with_their_outcomes_and_correlated() -> None:
    from bench.support import teamwork

    events: list[dict[str, Any]] = []
    for i, (est, got) in enumerate([(10.0, 12.0), (20.0, 18.0), (30.0, 33.0), (5.0, 0.0)]):
        events.append({"kind": "detour", "stamp_ns": i * 10**9, "robot_ids": ["r1"],
                       "message": "call (r2): ...: taken",
                       "figures": {"id": i + 1, "robot_s": 10.0, "cost_s": 4.0,
                                   "saving_s": est, "gain_s": 2 * est, "p": 0.5,
                                   "taken": 1.0}})
        events.append({"kind": "detour", "stamp_ns": (i + 5) * 10**9, "robot_ids": ["r1"],
                       "message": "call 1 by r1: ...",
                       "figures": {"id": i + 1, "measured_s": got, "saving_s": est,
                                   "after_s": 5.0}})
    events.append({"kind": "detour", "stamp_ns": 0, "robot_ids": ["r2"],
                   "message": "seek: ...: declined",
                   "figures": {"id": 9, "robot_s": 5.0, "cost_s": 9.0, "saving_s": 1.0,
                               "gain_s": 2.0, "p": 0.5, "taken": 0.0}})
    events.append({"kind": "merge", "stamp_ns": 0, "robot_ids": ["r1", "r2"], "message": "m"})
    pairs = teamwork.detour_pairs(events)
    assert [p["kind"] for p in pairs] == ["call"] * 4 + ["seek"]
    assert pairs[0]["measured_s"] == 12.0 and pairs[-1]["measured_s"] is None
    c = teamwork.correlation(pairs)
    assert c["decided"] == 5 and c["declined"] == 1
    assert c["call"]["n"] == 4 and c["call"]["pearson_r"] > 0.9
    assert c["call"]["spearman_r"] == 1.0
    assert c["call"]["paid"] == 3 and c["call"]["worth_and_paid"] == 3
    assert c["merge_kinds"]["n"] == 4


def test_a_team_is_judged_against_its_members_alone_on_the_same_seed() -> None:
    runs = keyed(run("1", 1, 200.0, robots=1), run("1", 2, 300.0, robots=1),
                 run("2-mixed", 1, 210.0, robots=2,
                     flat_coverage={"longest_s": 25.0, "team": "team-r1"}),
                 run("2-mixed", 2, 250.0, robots=2,
                     flat_coverage={"longest_s": 12.0, "team": "team-r1"}),
                 run("office-1", 1, 400.0, robots=1), run("office-3", 1, 150.0))
    tw = multi.teamwork_report(runs)
    mixed = tw["groups"]["2-mixed"]
    assert mixed["seeds"]["1"]["speedup"] == pytest.approx(200 / 210, abs=1e-3)
    assert mixed["seeds"]["1"]["no_slower"] is False
    assert mixed["seeds"]["2"]["no_slower"] is True
    assert mixed["never_slower"] is False
    assert mixed["flat_longest_s"] == 25.0 and mixed["flat_goal_met"] is False
    assert tw["groups"]["office-3"]["alone_case"] == "office-1"
    assert tw["groups"]["office-3"]["speedup_median"] == pytest.approx(400 / 150, abs=1e-3)
    assert "1" not in tw["groups"] and "office-1" not in tw["groups"]
