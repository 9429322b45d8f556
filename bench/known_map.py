"""Missions on a known map (docs/known-map.md): robots placed, wrong placements, lost robots
found again; prints JSON.

1. **The map**: the small house's, from a finished default demo (``mrslam demo``), made once
   and kept under ``--out`` (``demo/`` the run, ``map/`` its known_map folder); the map's
   frame lies in the world where the demo's anchor robot started.
2. **Placed**: per seed, ``--robots`` robots at random free poses (any heading), the server
   told nothing of where they are (``localize`` mode, the simulator and the server's core in
   lockstep, ``bench/support/known_mission.py``); each robot's time to be placed [s sim], and
   its error then against the truth. A placement farther than 0.5 m from the truth is wrong.
3. **Ambiguous wings**: the same in the self-similar world, on a map surveyed from the truth
   (exploring its 36 rooms would take too long here); wrong placements must be 0, a robot
   not placed within ``--wings-time`` waited for evidence.
4. **Lost**: a placed robot on its way to a random place is carried 5 m away (the simulator's
   teleport): when the server noticed (its ``robot_lost`` event), when it was placed again,
   its error then, and how far the map's keyframes moved meanwhile (the most the map's error
   against the truth can have changed).

5. **Missions in a row** (``--missions N`` alone): each on the map the one before left, its
   robots sent to random places for ``--mission-time``; the map's keyframes and the server's
   state after each (goal: within 1.5× of the first's).

    PYTHONPATH=. python bench/known_map.py [--seeds 10] [--first-seed 0] [--robots 3]
        [--wings-seeds 3] [--lost-seeds 5] [--out out/known_map]
    PYTHONPATH=. python bench/known_map.py --missions 4 [--mode extend|localize]

6. **A changed building** (``--changed``): the small house's map, the robots at the first
   exploration's spawns in ``small_house.changed`` (two doors closed, three boxes brought
   in), ``extend`` mode, the server's pass over the map on (``known_map.inspect``). The
   time until every change shows in the
   team's map (an occupied cell within 0.15 m of a closed door's centre, or of a box's
   sides) against the first exploration's time to its coverage (goal: 30 % or less), the
   ``map_changed`` regions farther than 1 m from every change (false changes), and the map's
   known area at the start, when every change is shown and at ``--changed-time`` (what the
   retired keyframes alone had shown is unknown until the robots see it again). Beside it,
   a bound from the world's truth (``bench.support.earliest``): when each change could be
   seen at the earliest, by the robot nearest it driving straight to a place in view of it
   from when it was placed, and the latest of them plus ``CHANGE_SPAN_S`` (the second view a
   change needs): no pass that does not know where the changes are can do better
   (``bound_up_to_date_s``; with several runs, ``bound_over_goal`` counts the spawns where
   even that misses the goal).

    PYTHONPATH=. python bench/known_map.py --changed [--changed-time 72] [--changed-seed N]
        [--changed-trace]

   With ``--changed-seeds default,1,2,3`` several runs (``default``: the first exploration's
   spawns, a number: random free spawns of that seed), each stopped once every change is
   shown, and a summary: each run's time against the first exploration's, the median, the
   worst and how many met the goal. ``--changed-trace`` (one run) adds when each change
   first got a vote and was confirmed, and each robot's pose, speed, turn rate and errand
   once a simulated second (``votes``, ``timeline``): what a slow run spent its time on.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

from bench.support.known_mission import (  # noqa: E402
    WORLDS,
    demo_config,
    free_poses,
    mission,
    pose_away,
)
from bench.support.survey import survey_map  # noqa: E402
from schemas.se2 import compose, inverse  # noqa: E402
from server.command.operator import OperatorCommand  # noqa: E402
from server.knownmap.changes import CHANGE_SPAN_S  # noqa: E402
from server.knownmap.ghosts import MAP_ID, MAP_TEAM  # noqa: E402
from server.knownmap.mapdata import KnownMap  # noqa: E402
from server.runtime.mapfind import find_map  # noqa: E402
from server.runtime.mapstore import read_map, write_map  # noqa: E402

HOUSE, WINGS = WORLDS / "small_house.world", WORLDS / "ambiguous_wings.world"
CHANGED = WORLDS / "small_house.changed.world"
GOALS = {"placed_within_s": 15.0, "placed_share": 0.9, "error_m": 0.10, "error_deg": 1.0,
         "wrong": 0, "noticed_s": 5.0, "placed_again_s": 20.0, "map_moved_m": 0.05}


def house_map(out: Path) -> tuple[KnownMap, np.ndarray, dict[str, Any]]:
    """The default demo's map (made once, then read from ``out/map``) and its world frame."""
    folder, run = out / "map", out / "demo"
    made: dict[str, Any] = {"cached": True}
    if not (folder / "map.json").exists():
        if not (run / "report.json").exists():
            t0 = time.monotonic()
            subprocess.run([sys.executable, "-m", "mrslam", "demo", "--out", str(run)],
                           cwd=_HERE.parent, check=True, stdout=subprocess.DEVNULL)
            made["demo_wall_s"] = round(time.monotonic() - t0, 1)
        known, _ = find_map(run, "small_house")
        spawn = json.loads((run / "report.json").read_text())["robots_spawn"][known.anchor]
        known.notes["world_frame"] = " ".join(f"{float(v):.6f}" for v in spawn)
        write_map(known, folder, "small_house", written_by="bench/known_map.py")
        made["cached"] = False
    known = read_map(folder, "small_house")
    frame = np.array([float(v) for v in known.notes["world_frame"].split()])
    return known, frame, {**made, "keyframes": len(known), "folder": str(folder)}


def placed_runs(known: KnownMap, frame: np.ndarray, world: Path, scenario: str,
                seeds: list[int], robots: int, limit_s: float) -> list[dict[str, Any]]:
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        spawn = {f"r{k + 1}": p for k, p in enumerate(free_poses(world, robots, rng))}
        m = mission(world, known, spawn, demo_config(scenario), frame, seed=seed)
        t0 = time.monotonic()
        want = set(spawn)
        m.run_until(limit_s, lambda m, want=want: {p.robot_id for p in m.placed} >= want)
        placed = {p.robot_id: p for p in m.placed}
        rows.append({
            "seed": seed, "wall_s": round(time.monotonic() - t0, 1),
            "robots": {rid: None if rid not in placed else {
                "placed_after_s": round(placed[rid].after_s, 1),
                "placed_at_s": round(placed[rid].at_s, 1),
                "error_m": round(placed[rid].error_m, 4),
                "error_deg": round(placed[rid].error_deg, 3)} for rid in spawn},
            "not_placed": sorted(set(spawn) - set(placed)),
            "lost": [[e.robot_ids[0], round(e.stamp_ns * 1e-9, 1)] for e in m.core.events.all
                     if e.kind == "robot_lost"],
            "refused": [e.message for e in m.core.events.all if e.kind == "merge_rejected"],
            "wrong": len(m.wrong()), "queries": m.core.known.counts["queries"]
            if m.core.known else 0})
        print(json.dumps(rows[-1]), file=sys.stderr)
    return rows


def lost_runs(known: KnownMap, frame: np.ndarray, seeds: list[int]) -> list[dict[str, Any]]:
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(1000 + seed)
        m = mission(HOUSE, known, {"r1": free_poses(HOUSE, 1, rng)[0]},
                    demo_config("small-house-3"), frame, seed=seed)
        m.run_until(30.0, lambda m: bool(m.placed))
        row: dict[str, Any] = {"seed": seed, "placed": bool(m.placed)}
        if m.placed:
            # on its way somewhere (an operator's goto in the map), then carried away
            goal = free_poses(HOUSE, 1, rng)[0]
            goal_map = _to_map(frame, goal)
            m.core.operate(OperatorCommand("goto", "r1", (float(goal_map[0]),
                                                          float(goal_map[1]))),
                           int(m.sim_time_s * 1e9))
            m.run_until(m.sim_time_s + 3.0)
            before = m.core.fleet.robots[MAP_ID].slam.keyframe_poses().copy()
            at = np.array(m.sim.robots["r1"].pose)
            m.sim.teleport("r1", tuple(pose_away(HOUSE, at, 5.0, rng)))
            t = m.sim_time_s
            m.run_until(t + 40.0, lambda m: len(m.placed) >= 2)
            lost = [e for e in m.core.events.all if e.kind == "robot_lost"]
            again = m.placed[1] if len(m.placed) > 1 else None
            moved = m.core.fleet.robots[MAP_ID].slam.keyframe_poses() - before
            row.update({
                "noticed_s": round(lost[0].stamp_ns * 1e-9 - t, 1) if lost else None,
                "placed_again_s": None if again is None else round(again.at_s - t, 1),
                "error_m": None if again is None else round(again.error_m, 4),
                "error_deg": None if again is None else round(again.error_deg, 3),
                "map_moved_m": round(float(np.hypot(moved[:, 0], moved[:, 1]).max()), 5),
                "wrong": len(m.wrong())})
        print(json.dumps(row), file=sys.stderr)
        rows.append(row)
    return rows


def mission_chain(known: KnownMap, frame: np.ndarray, missions: int, mode: str,
                  duration_s: float) -> list[dict[str, Any]]:
    """Missions in a row, each on the map the one before left: 3 robots at random free poses,
    placed, then each sent to random free places for ``duration_s``; the map's keyframes and
    the server's state (pickled core) after each."""
    import pickle

    rows = []
    for k in range(missions):
        rng = np.random.default_rng(2000 + k)
        spawn = {f"r{i + 1}": p for i, p in enumerate(free_poses(HOUSE, 3, rng))}
        m = mission(HOUSE, known, spawn, demo_config("small-house-3", mode=mode), frame,
                    seed=k)
        t0 = time.monotonic()
        while m.sim_time_s < duration_s:
            m.step()
            if m.steps % 50:
                continue
            for rid in spawn:       # a placed robot with nothing to do is sent somewhere
                r = m.core.robots[rid]
                if m._placed(rid) and r.nav.target_xy is None:
                    g = _to_map(frame, free_poses(HOUSE, 1, rng)[0])
                    m.core.operate(OperatorCommand("goto", rid, (float(g[0]), float(g[1]))),
                                   int(m.sim_time_s * 1e9))
        assert m.core.known is not None
        left = m.core.known.mission_map()
        assert left is not None
        from server.slam.mapping import render_grid
        mapped = render_grid(m.core.fleet.stages.mapper().params, left.keyframes, left.poses)
        rows.append({"mission": k + 1, "placed": len(m.placed), "keyframes_before": len(known),
                     "keyframes_after": len(left), "map_known_m2": _known_m2(mapped),
                     "state_mb": round(len(pickle.dumps(m.core, protocol=5)) / 1e6, 2),
                     "upkeep": m.core.known.summary().get("upkeep"),
                     "robots_lost": m.core.known.counts["lost"],
                     "wall_s": round(time.monotonic() - t0, 1)})
        print(json.dumps(rows[-1]), file=sys.stderr)
        known = left
    return rows


def changed_run(known: KnownMap, frame: np.ndarray, first_s: float, limit_s: float,
                go_on: bool = True, seed: int | None = None,
                trace: bool = False) -> dict[str, Any]:
    """The map brought up to date in the changed house (see the module docstring, 6)."""
    from sim.config import DEFAULT_SCENARIOS, load_scenario
    from sim.floorplan import SMALL_HOUSE_BOXES, SMALL_HOUSE_CLOSED

    changes = [("door", x, y, 0.15) for x, y in SMALL_HOUSE_CLOSED] + \
        [("box", b[0], b[1], 0.5 * max(b[3], b[4]) + 0.15) for b in SMALL_HOUSE_BOXES]
    spawn = {rid: np.array(p, dtype=float) for rid, p in
             load_scenario(DEFAULT_SCENARIOS, "small-house-3")["robots"].items()}
    if seed is not None:        # random free poses instead of the first exploration's spawns
        rng = np.random.default_rng(seed)
        spawn = {f"r{k + 1}": np.asarray(p, dtype=float)
                 for k, p in enumerate(free_poses(CHANGED, 3, rng))}
    m = mission(CHANGED, known, spawn, demo_config("small-house-3", mode="extend"), frame)
    at = [_to_map(frame, np.array([x, y, 0.0]))[:2] for _, x, y, _ in changes]
    shown: dict[int, float] = {}
    known_m2 = [_known_m2(m.core.fleet.team_grid(MAP_TEAM))]
    timeline: list[dict[str, Any]] = []
    votes: dict[int, dict[str, float]] = {}
    t0 = time.monotonic()
    while m.sim_time_s < limit_s:
        m.step()
        if m.steps % 10:
            continue
        if trace:
            _trace(m, frame, changes, at, votes, timeline)
        grid = m.core.fleet.team_grid(MAP_TEAM)
        for k, ((_, _, _, r), xy) in enumerate(zip(changes, at, strict=True)):
            if k not in shown and _occupied_near(grid, xy, r):
                shown[k] = round(m.sim_time_s, 1)
                if len(shown) == len(changes):
                    known_m2.append(_known_m2(grid))
        if len(shown) == len(changes) and not go_on:
            break
    regions = [e.figures or {} for e in m.core.events.all if e.kind == "map_changed"]
    false = [g for g in regions if min(math.hypot((g["x0"] + g["x1"]) / 2 - xy[0],
                                                  (g["y0"] + g["y1"]) / 2 - xy[1])
                                       for xy in at) > 1.0]
    up_to_date = max(shown.values()) if len(shown) == len(changes) else None
    bound = _earliest(spawn, {p.robot_id: p.at_s for p in m.placed}, changes)
    known_m2.append(_known_m2(m.core.fleet.team_grid(MAP_TEAM)))
    still = [k for k, (_, _, _, r) in enumerate(changes) if k in shown and not
             _occupied_near(m.core.fleet.team_grid(MAP_TEAM), at[k], r)]
    assert m.core.known is not None
    return {"first_exploration_s": first_s, "spawn_seed": seed,
            "changes": [{"what": w, "x": x, "y": y, "shown_at_s": shown.get(k)}
                        for k, (w, x, y, _) in enumerate(changes)],
            "all_shown": len(shown) == len(changes), "up_to_date_s": up_to_date,
            "vs_first": None if up_to_date is None else round(up_to_date / first_s, 3),
            "goal_vs_first": 0.30,
            # the earliest each change could be seen, knowing where it is (bench.support.
            # earliest), and all of them confirmed (a second view CHANGE_SPAN_S later)
            "earliest_sight_s": [round(t, 1) for t in bound],
            "bound_up_to_date_s": round(max(bound) + CHANGE_SPAN_S, 1),
            "bound_vs_first": round((max(bound) + CHANGE_SPAN_S) / first_s, 3),
            "placed": len(m.placed),
            "map_changed_regions": len(regions), "false_changes": len(false),
            "false_changes_at_world": [
                [round(float(v), 2) for v in compose(frame, np.array(
                    [(g["x0"] + g["x1"]) / 2, (g["y0"] + g["y1"]) / 2, 0.0]))[:2]]
                + [int(g["cells"])] for g in false],
            "upkeep": m.core.known.summary().get("upkeep"),
            "keyframes_left": len(m.core.known.mission_map() or []),
            "map_known_m2": dict(zip(["start", "all_shown", "end"] if len(known_m2) == 3
                                     else ["start", "end"], known_m2, strict=True)),
            "shown_then_lost": len(still),
            # a placed robot taken for lost here is a false alarm: nobody moved it
            "robots_lost": m.core.known.counts["lost"],
            "sim_s": round(m.sim_time_s, 1), "wall_s": round(time.monotonic() - t0, 1),
            **({"votes": {f"{changes[k][0]} ({changes[k][1]}, {changes[k][2]})": v
                          for k, v in sorted(votes.items())},
                "timeline": timeline} if trace else {})}


def _earliest(spawn: dict[str, np.ndarray], placed_s: dict[str, float],
              changes: list[tuple[str, float, float, float]]) -> list[float]:
    """``bench.support.earliest`` for a changed-house run: the robots from their spawns, each
    from when it was placed, at the pursuit's speed, the simulator's LIDAR range."""
    from bench.support.earliest import earliest_sight_s
    from server.control.pure_pursuit import PursuitParams
    from server.control.vfh import VfhParams
    from sim.simulator import SimParams

    vfh = VfhParams()
    starts = {rid: (float(p[0]), float(p[1]), placed_s[rid]) for rid, p in spawn.items()
              if rid in placed_s}
    return earliest_sight_s(CHANGED, starts, [(x, y, max(r - 0.15, 0.2)) for _, x, y, r in changes],
                            PursuitParams().v_mps, SimParams().lidar.range_max_m,
                            vfh.robot_radius_m + vfh.safety_m)


def _trace(m: Any, frame: np.ndarray, changes: list[tuple[str, float, float, float]],
           at: list[np.ndarray], votes: dict[int, dict[str, float]],
           timeline: list[dict[str, Any]]) -> None:
    """``--changed-trace``: when each change first got a vote and was confirmed (votes for
    cells within its size + 0.1 m), and once a simulated second each robot's true pose, its
    state, speed, turn rate and errand (kind, goal in the world, way left along its path)."""
    from server.core import _left_m

    t = round(m.sim_time_s, 1)
    up = m.core.known.upkeep
    older = m.core.known.view().older
    if up is not None and older is not None:
        step = older.fine_m
        for k, ((_, _, _, r), xy) in enumerate(zip(changes, at, strict=True)):
            for key in up.votes:
                c = ((key[2] + 0.5) * step, (key[1] + 0.5) * step)
                if math.hypot(c[0] - xy[0], c[1] - xy[1]) <= r + 0.1:
                    votes.setdefault(k, {}).setdefault("first_vote_s", t)
                    if key in up.confirmed:
                        votes[k].setdefault("confirmed_s", t)
    if timeline and int(t) == int(timeline[-1]["t"]):
        return
    row: dict[str, Any] = {"t": t}
    for rid, sr in m.sim.robots.items():
        r = m.core.robots.get(rid)
        placed = r is not None and r.team_id == MAP_TEAM
        e = m.core.orders.errands.get(rid)
        row[rid] = {"at": [round(float(sr.pose[0]), 2), round(float(sr.pose[1]), 2),
                           round(math.degrees(sr.pose[2]))],
                    "placed": placed, "v": round(sr.v, 2), "w": round(sr.w, 2)}
        if e is not None and placed and r is not None:
            g = compose(frame, np.array([*e.goal_xy, 0.0]))
            row[rid]["errand"] = {"kind": e.kind, "goal": [round(float(g[0]), 2),
                                                           round(float(g[1]), 2)],
                                  "left_m": round(_left_m(e.path_xy, r.pose), 2)}
    timeline.append(row)


def changed_summary(runs: list[dict[str, Any]], first_s: float) -> dict[str, Any]:
    """Several changed-house runs (``--changed-seeds``): each one's time to bring the map up
    to date and when each change was shown."""
    ratios = [r["vs_first"] for r in runs if r["vs_first"] is not None]
    return {"first_exploration_s": first_s, "goal_vs_first": 0.30,
            "runs": [{"spawn_seed": r["spawn_seed"], "up_to_date_s": r["up_to_date_s"],
                      "vs_first": r["vs_first"], "placed": r["placed"],
                      "shown_at_s": [c["shown_at_s"] for c in r["changes"]],
                      "earliest_sight_s": r["earliest_sight_s"],
                      "bound_up_to_date_s": r["bound_up_to_date_s"],
                      "false_changes": r["false_changes"], "robots_lost": r["robots_lost"],
                      "wall_s": r["wall_s"]}
                     for r in runs],
            # spawns where even a team knowing where the changes are could not meet the goal
            "bound_over_goal": sum(r["bound_vs_first"] > 0.30 for r in runs),
            "all_shown": sum(r["all_shown"] for r in runs), "of": len(runs),
            "vs_first_median": round(float(np.median(ratios)), 3) if ratios else None,
            "vs_first_max": max(ratios) if len(ratios) == len(runs) else None,
            "met": sum(r["vs_first"] is not None and r["vs_first"] <= 0.30 for r in runs),
            "false_changes": sum(r["false_changes"] for r in runs),
            "robots_lost": sum(r["robots_lost"] for r in runs)}


def _known_m2(grid: Any) -> float:
    return round(float(grid.observed.sum()) * grid.resolution_m ** 2, 1)


def _occupied_near(grid: Any, xy: np.ndarray, r: float) -> bool:
    """Any occupied cell of ``grid`` within ``r`` of ``xy``."""
    lo, hi = grid.cell_of(np.array([xy - r, xy + r]))
    occ = grid.occupied_mask()
    h, w = occ.shape
    return bool(occ[max(lo[1], 0):min(hi[1] + 1, h), max(lo[0], 0):min(hi[0] + 1, w)].any())


def _to_map(frame: np.ndarray, p: np.ndarray) -> np.ndarray:
    return compose(inverse(frame), p)


def _share(values: list[bool]) -> float | None:
    return round(sum(values) / len(values), 3) if values else None


def summarise(house: list[dict[str, Any]], wings: list[dict[str, Any]],
              lost: list[dict[str, Any]]) -> dict[str, Any]:
    placed = [r for row in house for r in row["robots"].values() if r is not None]
    all_robots = [r for row in house for r in row["robots"].values()]
    in_time = [r is not None and r["placed_after_s"] <= GOALS["placed_within_s"]
               for r in all_robots]
    runs_in_time = [all(r is not None and r["placed_after_s"] <= GOALS["placed_within_s"]
                        for r in row["robots"].values()) for row in house]
    found = [r for r in lost if r.get("placed_again_s") is not None]
    out = {
        "house": {
            "runs": len(house), "robots": len(all_robots), "placed": len(placed),
            "runs_all_placed_within_15s": sum(runs_in_time),
            "share_of_runs_all_placed_within_15s": _share(runs_in_time),
            "share_of_robots_placed_within_15s": _share(in_time),
            "placed_after_s_median": _q(placed, "placed_after_s", 50),
            "placed_after_s_max": _q(placed, "placed_after_s", 100),
            "error_m_max": _q(placed, "error_m", 100),
            "error_deg_max": _q(placed, "error_deg", 100),
            "wrong": sum(row["wrong"] for row in house)},
        "wings": {
            "runs": len(wings), "placed": sum(r is not None for row in wings
                                              for r in row["robots"].values()),
            "wrong": sum(row["wrong"] for row in wings),
            "error_m_max": _q([r for row in wings for r in row["robots"].values()
                               if r is not None], "error_m", 100)},
        "lost": {
            "runs": len(lost), "noticed": sum(r.get("noticed_s") is not None for r in lost),
            "placed_again": len(found),
            "noticed_s_max": _q([r for r in lost if r.get("noticed_s") is not None],
                                "noticed_s", 100),
            "placed_again_s_median": _q(found, "placed_again_s", 50),
            "placed_again_s_max": _q(found, "placed_again_s", 100),
            "error_m_max": _q(found, "error_m", 100),
            "map_moved_m_max": _q([r for r in lost if "map_moved_m" in r], "map_moved_m",
                                  100),
            "wrong": sum(r.get("wrong", 0) for r in lost)},
    }
    h, w, lo = out["house"], out["wings"], out["lost"]
    out["goals_met"] = {
        "placed_within_15s_in_9_of_10_runs": (h["share_of_runs_all_placed_within_15s"] or 0)
        >= GOALS["placed_share"],
        "placement_error": h["error_m_max"] is not None and h["error_m_max"] <= 0.10
        and h["error_deg_max"] <= 1.0,
        "no_wrong_placement": h["wrong"] == 0 and w["wrong"] == 0 and lo["wrong"] == 0,
        "lost_noticed_within_5s": lo["noticed"] == lo["runs"] and lo["runs"] > 0
        and (lo["noticed_s_max"] or 0) <= GOALS["noticed_s"],
        "placed_again_within_20s": lo["placed_again"] == lo["runs"] and lo["runs"] > 0
        and (lo["placed_again_s_max"] or 0) <= GOALS["placed_again_s"],
        "map_unchanged": (lo["map_moved_m_max"] or 0) <= GOALS["map_moved_m"]}
    return out


def _q(rows: list[dict[str, Any]], key: str, pct: float) -> float | None:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return round(float(np.percentile(vals, pct)), 4) if vals else None


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10, help="small-house runs")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--robots", type=int, default=3, help="robots per small-house run")
    ap.add_argument("--limit", type=float, default=40.0, help="sim seconds per run at most")
    ap.add_argument("--wings-seeds", type=int, default=3)
    ap.add_argument("--wings-time", type=float, default=60.0)
    ap.add_argument("--lost-seeds", type=int, default=5)
    ap.add_argument("--out", type=Path, default=_HERE.parent / "out" / "known_map")
    ap.add_argument("--missions", type=int, default=0, help="only missions in a row, each on "
                    "the map the one before left: the map's and the state's size")
    ap.add_argument("--mode", default="extend", help="with --missions: localize or extend")
    ap.add_argument("--mission-time", type=float, default=30.0)
    ap.add_argument("--changed", action="store_true", help="only the changed house: the "
                    "time to bring the map up to date against the first exploration's")
    ap.add_argument("--changed-time", type=float, default=72.0, help="sim seconds at most")
    ap.add_argument("--changed-seed", type=int, default=None, help="with --changed: the robots "
                    "at random free poses of this seed (default: the first exploration's spawns)")
    ap.add_argument("--changed-trace", action="store_true",
                    help="with --changed: when each change first got a vote and was "
                    "confirmed, and each robot's pose, speed and errand once a second")
    ap.add_argument("--changed-seeds", default=None, help="with --changed: several runs, "
                    "comma-separated spawn seeds ('default': the first exploration's "
                    "spawns), each stopped once every change is shown; a summary")
    a = ap.parse_args()
    t0 = time.monotonic()
    if not (a.changed or a.missions or a.seeds or a.lost_seeds):   # the wings alone
        known: Any = None           # the house's map is not needed
        frame, made = np.zeros(3), {"cached": None}
    else:
        known, frame, made = house_map(a.out)
    if a.changed and a.changed_seeds:
        first_s = float(json.loads((a.out / "demo" / "report.json").read_text())
                        ["first_team_time_to_threshold_s"])
        runs = [changed_run(known, frame, first_s, a.changed_time, go_on=False,
                            seed=None if v == "default" else int(v))
                for v in a.changed_seeds.split(",")]
        print(json.dumps({"map": made, **changed_summary(runs, first_s),
                          "wall_s": round(time.monotonic() - t0, 1)}, indent=2))
        return
    if a.changed:
        first = json.loads((a.out / "demo" / "report.json").read_text())
        row = changed_run(known, frame, float(first["first_team_time_to_threshold_s"]),
                          a.changed_time, seed=a.changed_seed, trace=a.changed_trace)
        print(json.dumps({"map": made, **row, "wall_s": round(time.monotonic() - t0, 1)},
                         indent=2))
        return
    if a.missions:
        rows = mission_chain(known, frame, a.missions, a.mode, a.mission_time)
        first = rows[0]["state_mb"]
        print(json.dumps({"map": made, "mode": a.mode, "missions": rows,
                          "state_vs_first_max": round(max(r["state_mb"] for r in rows)
                                                      / first, 2),
                          "goal_state_vs_first": 1.5,
                          "wall_s": round(time.monotonic() - t0, 1)}, indent=2))
        return
    seeds = list(range(a.first_seed, a.first_seed + a.seeds))
    house = [] if not seeds else \
        placed_runs(known, frame, HOUSE, "small-house-3", seeds, a.robots, a.limit)
    wings_map = survey_map(WINGS)
    wings = placed_runs(wings_map, np.zeros(3), WINGS, "ambiguous-2",
                        list(range(a.first_seed, a.first_seed + a.wings_seeds)), 1,
                        a.wings_time)
    lost = lost_runs(known, frame, list(range(a.first_seed, a.first_seed + a.lost_seeds)))
    print(json.dumps({"map": made, "goals": GOALS, **summarise(house, wings, lost),
                      "runs": {"house": house, "wings": wings, "lost": lost},
                      "wall_s": round(time.monotonic() - t0, 1)}, indent=2))


if __name__ == "__main__":
    main()
