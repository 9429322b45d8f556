"""``report.json`` of a demo run: the server's outputs scored against the simulator's truth."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from mrslam.run_files import Gaps, read_json, read_trajectory, read_truth
from schemas.se2 import compose, inverse, pose_distance
from server.knownmap.ghosts import MAP_ID
from server.offline.scoring import anchor_transform, ate_rmse, map_quality, match_truth, pose_errors

log = logging.getLogger(__name__)


def _finite(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 4)


#: a committed merge farther than this from the truth joined maps wrongly
FALSE_MERGE_M, FALSE_MERGE_RAD = 0.5, math.radians(5.0)


def _own_frame(stamps: np.ndarray, online: np.ndarray, t: dict[str, Any]) -> np.ndarray:
    idx, true_first = match_truth(stamps[:1], t["stamps_ns"], t["poses"])
    return anchor_transform(true_first[0], online[0]) if len(idx) else np.zeros(3)


def _in_team_error(rid: str, folder: Path, own_frames: dict[str, np.ndarray],
                   truth: dict[str, Any], gaps: Gaps) -> float | None:
    """The largest position error of ``rid``'s online poses while in a team, as the team's
    map placed it: in the own frame of the team's first robot (``<rid>_online_in_<first>``),
    that frame placed in the world by the first robot's start. None if it was never in a
    team, or if its truth or its first robot's is unknown."""
    t = truth.get(rid)
    if t is None:
        return None
    worst = None
    for path in sorted(folder.glob(f"{rid}_online_in_*.csv")):
        first = path.stem[len(f"{rid}_online_in_"):]
        if first not in own_frames:
            continue
        stamps, poses = read_trajectory(path, gaps)
        if not len(stamps):
            continue
        err = pose_errors(stamps, poses, own_frames[first], t["stamps_ns"], t["poses"])
        if len(err.position_m):
            worst = max(worst or 0.0, float(err.position_m.max()))
    return _finite(worst) if worst is not None else None


def _transform_error(T: Any, T_true: np.ndarray) -> tuple[float, float]:
    return pose_distance(compose(inverse(T_true), np.asarray(T, dtype=np.float64)))


def _pose_at(stamps: np.ndarray, poses: np.ndarray, stamp_ns: int) -> np.ndarray | None:
    """The pose nearest to ``stamp_ns`` (within 0.2 s), or None."""
    idx, found = match_truth([stamp_ns], stamps, poses, tolerance_ns=200_000_000)
    return found[0] if len(idx) else None


def merge_errors(merges: list[dict[str, Any]], own_frames: dict[str, np.ndarray],
                 final: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                 truth: dict[str, Any] | None = None,
                 first_online: dict[str, np.ndarray] | None = None,
                 final_team: dict[str, str] | None = None) -> list[dict[str, Any]]:
    """Each merge's transform (b's team frame -> a's) against the truth: after the joint
    optimisation, fused sightings, and the direct method on the first sighting. The transform
    between the two start frames also carries each robot's drift until they met, so
    ``meeting_error`` adds how well the final joint map places the two robots that met
    relative to each other at the merge (when they ended in one team), and ``final_error``
    the same start-frame transform as the final joint map has it: the joint optimisation goes
    on after the merge (matches of each robot's scans against the other's map), and this is
    what it made of the transform in the end."""
    out = []
    for m in merges:
        a, b = m["robots_a"][0], m["robots_b"][0]
        row: dict[str, Any] = {"sim_time_s": round(m["stamp_ns"] * 1e-9, 2),
                               "team_id": m["team_id"], "joined_team_id": m["joined_team_id"],
                               "robots": m["robots_a"] + m["robots_b"],
                               "kind": m.get("kind", "tags"),
                               "sightings": len(m["sightings"]),
                               "undone": m.get("undone_stamp_ns") is not None,
                               "map_agreement": m.get("map_agreement")}
        if a in own_frames and b in own_frames:
            T_true = compose(inverse(own_frames[a]), own_frames[b])
            for name, key in (("joint", "T_joint"), ("fused", "T_fused"),
                              ("direct", "T_direct_first")):
                et, er = _transform_error(m[key], T_true)
                row[f"{name}_error_m"] = round(et, 4)
                row[f"{name}_error_deg"] = round(math.degrees(er), 3)
            row["false_merge"] = (row["joint_error_m"] > FALSE_MERGE_M
                            or math.radians(row["joint_error_deg"]) > FALSE_MERGE_RAD)
        both = {a, b}
        if final and first_online and final_team and both <= own_frames.keys() \
                and both <= first_online.keys() and both <= final_team.keys() \
                and final_team[a] == final_team[b] and m.get("undone_stamp_ns") is None \
                and len(final.get(a, ((), ()))[1]) and len(final.get(b, ((), ()))[1]):
            # each own frame in the final team frame: first final pose ∘ first online pose⁻¹
            Fa = compose(final[a][1][0], inverse(first_online[a]))
            Fb = compose(final[b][1][0], inverse(first_online[b]))
            et, er = _transform_error(compose(inverse(Fa), Fb),
                                      compose(inverse(own_frames[a]), own_frames[b]))
            row["final_error_m"] = round(et, 4)
            row["final_error_deg"] = round(math.degrees(er), 3)
        if final and truth and m["sightings"] and m.get("undone_stamp_ns") is None:
            o, s, _ = m["sightings"][-1]
            est = [_pose_at(*final[r], m["stamp_ns"]) if r in final else None for r in (o, s)]
            tru = [_pose_at(np.asarray(truth[r]["stamps_ns"]), np.asarray(truth[r]["poses"]),
                            m["stamp_ns"]) if r in truth else None for r in (o, s)]
            eo, es, to, ts = (*est, *tru)
            if eo is not None and es is not None and to is not None and ts is not None:
                et, er = _transform_error(compose(inverse(eo), es), compose(inverse(to), ts))
                row["meeting_error_m"] = round(et, 4)
                row["meeting_error_deg"] = round(math.degrees(er), 3)
        out.append(row)
    return out


SIGHT_RANGE_M = 10.0   # the farthest a tag is read (and LIDAR-located) in the simulator


def first_sight(merges: list[dict[str, Any]], truth: dict[str, Any], segments: np.ndarray,
                circles: np.ndarray | None = None, within_m: float = SIGHT_RANGE_M
                ) -> list[float | None]:
    """For each merge, the first sim time [s] at which a robot of one side had a robot of the
    other within ``within_m`` and nothing but air between them (the truth against the world's
    walls), or None if never before the merge: the earliest the two teams could have met.
    A merge long after it was slow to see or verify; one right after it waited on the meeting."""
    from sim.raycast import line_of_sight

    out: list[float | None] = []
    for m in merges:
        end = m["stamp_ns"]
        best: int | None = None
        for ra in m["robots_a"]:
            for rb in m["robots_b"]:
                if ra not in truth or rb not in truth:
                    continue
                sa = np.asarray(truth[ra]["stamps_ns"], dtype=np.int64)
                pa = np.asarray(truth[ra]["poses"], dtype=np.float64)
                sb = np.asarray(truth[rb]["stamps_ns"], dtype=np.int64)
                pb = np.asarray(truth[rb]["poses"], dtype=np.float64)
                if not len(sa) or not len(sb):
                    continue
                keep = sa <= (end if best is None else best)
                sa, pa = sa[keep], pa[keep]
                j = np.clip(np.searchsorted(sb, sa), 0, len(sb) - 1)
                near = np.flatnonzero(np.hypot(*(pa[:, :2] - pb[j, :2]).T) <= within_m)
                for i in near:
                    if line_of_sight(tuple(pa[i, :2]), tuple(pb[j[i], :2]), segments, circles):
                        best = int(sa[i])
                        break
        out.append(round(best * 1e-9, 2) if best is not None else None)
    return out


def threshold_times(teams: dict[str, Any]) -> tuple[bool, float | None, float | None]:
    """Whether the run reached its threshold, when (the last of the final teams), and when
    the first team did: a team merged into another later counts for the first (its robots
    had mapped that much together), not for the run."""
    final = [t for t in teams.values() if not t.get("merged_into")]
    reached = bool(final) and all(t["reached"] for t in final)
    times = [t["sim_time_to_threshold_s"] for t in final]
    best = max(times) if times and None not in times else None
    first = min((t["sim_time_to_threshold_s"] for t in teams.values()
                 if t.get("sim_time_to_threshold_s") is not None), default=None)
    return reached, best, first


def build_report(cfg: Any, plan: dict[str, Any], out: Path, watch: dict[str, Any],
                 wall_time_s: float, figures: bool = True) -> dict[str, Any]:
    """Score the run folder ``out``. Whatever is missing or damaged (the server's outputs
    when it died for good) is left out and named under ``missing``; the rest still counts.
    ``figures`` False: no figures (a run stopped by a signal ends without waiting for
    them)."""
    from sim.errors import WorldError
    from sim.grid import read_nav2

    gaps = Gaps(out)
    server_dir = out / "server"
    summary = read_json(server_dir / "summary.json", gaps)
    if summary.get("running"):
        gaps.note(server_dir / "summary.json", "written while the server ran (its last "
                  "periodic refresh): the server did not stop cleanly")
    truth = read_truth(out / "sim" / "truth.jsonl", gaps)
    if truth:
        write_truth_tum(truth, out / "sim" / "trajectories")

    def trajectory(rid: str, kind: str) -> tuple[np.ndarray, np.ndarray]:
        return read_trajectory(server_dir / "trajectories" / f"{rid}_{kind}.csv", gaps)

    threshold = plan["threshold"]
    robots: dict[str, Any] = {}
    teams: dict[str, Any] = {}
    own_frames: dict[str, np.ndarray] = {}
    first_online: dict[str, np.ndarray] = {}
    final_team: dict[str, str] = {}
    for team_id, team in summary.get("teams", {}).items():
        robot_ids = list(team.get("robot_ids", []))
        T_world_map = np.zeros(3)
        if robot_ids and robot_ids[0] in truth:
            anchor = robot_ids[0]
            a_stamps, a_online = trajectory(anchor, "online")
            idx, a_true = match_truth(a_stamps[:1], truth[anchor]["stamps_ns"],
                                      truth[anchor]["poses"])
            if len(idx):
                T_world_map = anchor_transform(a_true[0], a_online[0])
        elif robot_ids and robot_ids[0] == MAP_ID and plan.get("map_frame") is not None:
            T_world_map = np.asarray(plan["map_frame"], dtype=np.float64)   # a known map's
        history = team.get("coverage_history", [])
        t_reach = next((s * 1e-9 for s, c in history if c >= threshold), None)
        quality = None
        map_yaml = server_dir / "maps" / team_id / "map.yaml"
        if map_yaml.exists():
            try:
                est = read_nav2(map_yaml)
            except WorldError as e:
                gaps.note(map_yaml, f"map not scored: {e}")
            else:
                tg = plan["truth_grid"]
                q = map_quality(est.cells, est.resolution_m, est.origin[:2], T_world_map,
                                tg.cells, tg.resolution_m, tg.origin[:2])
                quality = {"true_coverage": _finite(q.true_coverage),
                           "explored_free_m2": _finite(q.explored_free_m2),
                           "true_free_m2": _finite(q.true_free_m2),
                           "phantom_area_m2": _finite(q.phantom_area_m2)}
        else:
            gaps.note(map_yaml, "missing")
        teams[team_id] = {"robot_ids": robot_ids, "coverage": _finite(team.get("coverage")),
                          "reached": t_reach is not None,
                          "sim_time_to_threshold_s": None if t_reach is None else _finite(t_reach),
                          "coverage_history": [[s * 1e-9, c] for s, c in history],
                          **(quality or {})}
        for rid in robot_ids:
            t = truth.get(rid)
            if t is None:
                continue
            stamps, online = trajectory(rid, "online")
            f_stamps, final = trajectory(rid, "final")
            # online poses are in the robot's own map frame (its first pose is the origin)
            T_world_own = own_frames[rid] = _own_frame(stamps, online, t)
            if len(online):
                first_online[rid] = np.asarray(online[0], dtype=np.float64)
                final_team[rid] = team_id
            err = pose_errors(stamps, online, T_world_own, t["stamps_ns"], t["poses"])
            srv = summary.get("robots", {}).get(rid, {})
            robots[rid] = {
                "team_id": team_id,
                **_truth_row(t, watch, rid),
                "max_position_error_m": _finite(err.max_position_m),
                "max_yaw_error_rad": _finite(err.max_yaw_rad),
                "ate_rmse_m": _finite(ate_rmse(f_stamps, final, t["stamps_ns"], t["poses"])),
                **{k: srv.get(k) for k in SERVER_ROBOT_FIELDS},
                "_errors": (err.stamps_ns * 1e-9, err.position_m, err.yaw_rad),
            }
    for rid, t in truth.items():   # robots the server's outputs do not tell of
        robots.setdefault(rid, {"team_id": None, **_truth_row(t, watch, rid),
                                "max_position_error_m": None, "max_yaw_error_rad": None,
                                "ate_rmse_m": None, **dict.fromkeys(SERVER_ROBOT_FIELDS)})
    for rid, row in robots.items():
        row["max_team_position_error_m"] = _in_team_error(
            rid, server_dir / "trajectories", own_frames, truth, gaps)
    final_traj = {rid: trajectory(rid, "final") for rid in summary.get("robots", {})
                  if (server_dir / "trajectories" / f"{rid}_final.csv").exists()}
    merges = merge_errors(summary.get("merges", []), own_frames, final_traj, truth,
                          first_online, final_team)
    from sim.loader import load_world

    try:
        world = load_world(plan["world"])
        sights = first_sight(summary.get("merges", []), truth, world.segments, world.circles)
        for row, t_sight in zip(merges, sights, strict=True):
            row["first_sight_s"] = t_sight
    except WorldError as e:   # a scoring extra: the report stands without it
        log.warning("first line of sight per merge not scored: %s", e)
    for tid, old in summary.get("merged_teams", {}).items():
        hist = old.get("coverage_history", [])
        # a team may reach the threshold before a robot still alone joins it
        t_old = next((s * 1e-9 for s, c in hist if c >= threshold), None)
        teams.setdefault(tid, {"robot_ids": old.get("robot_ids", []),
                               "merged_into": old.get("merged_into"),
                               "coverage": _finite(hist[-1][1]) if hist else None,
                               "reached": t_old is not None,
                               "sim_time_to_threshold_s": None if t_old is None else _finite(t_old),
                               "coverage_history": [[s * 1e-9, c] for s, c in hist]})
    reached, best, first = threshold_times(teams)
    hypotheses = hypothesis_errors(summary.get("map_hypotheses", []), own_frames)
    qms = summary.get("map_query_ms", [])
    report = {
        "scenario": plan["title"], "world": plan["world"], "seed": cfg.seed,
        "explorer": cfg.explorer, "lockstep": cfg.lockstep,
        "robots_spawn": plan["robots"], "threshold": threshold,
        "area_m2": plan["area_m2"], "nominal_area_m2": plan["nominal_area_m2"],
        "reached": reached,
        "sim_time_to_threshold_s": best,
        # the first team whose own map reached the threshold (other teams may still explore)
        "first_team_time_to_threshold_s": first,
        "true_coverage": min((t.get("true_coverage") or 0.0 for t in teams.values()
                              if not t.get("merged_into")), default=None),
        "phantom_area_m2": sum(t.get("phantom_area_m2") or 0.0 for t in teams.values()
                               if not t.get("merged_into")),
        "teams": teams, "robots": robots,
        "wall_time_s": round(wall_time_s, 2), "end": watch.get("end"),
        "sim_time_s": round(watch.get("sim_time_s", 0.0), 2),
        "merges": merges,
        "false_merges": sum(1 for m in merges if is_false_merge(m)),
        "hypotheses": hypotheses,
        "map_query_ms_median": round(float(np.median(qms)), 1) if qms else None,
        "tag_counters": summary.get("tag_counters", {}),
        # without the server's summary, the events the bus carried
        "events": summary.get("events", watch.get("events", [])),
        "exit_codes": watch.get("exit_codes", {}),
        "server_restarts": watch.get("server_restarts", []),
        "missing": gaps.notes,
        # only a case of the dissertation's own scenarios file has its published figures
        **({"dissertation": beside_dissertation(plan["title"], plan["reported"], robots)}
           if plan.get("reported") else {}),
    }
    if not figures:
        gaps.note(out / "figures", "not drawn: the run was stopped by a signal")
        return _without_errors(report, robots)
    try:
        from mrslam.figures import write_figures

        report["figures"] = write_figures(report, out, gaps)
    except Exception:  # figures are a convenience; the numbers above are the result
        log.exception("could not draw the figures")
    return _without_errors(report, robots)


def beside_dissertation(case: str, reported: dict[str, Any], robots: dict[str, Any]
                        ) -> dict[str, Any]:
    """The figures the dissertation published for ``case`` (its scenarios file's
    ``reported``), beside ours of the same kind over all robots: the largest online yaw error,
    and the largest online position error (the distance, so no smaller than the x and y
    errors it gives apart)."""
    def largest(key: str) -> float | None:
        values = [r[key] for r in robots.values() if r.get(key) is not None]
        return max(values) if values else None

    return {"case": case, "reported": dict(reported),
            "measured": {"max_position_error_m": largest("max_position_error_m"),
                         "max_yaw_error_rad": largest("max_yaw_error_rad")}}


def _without_errors(report: dict[str, Any], robots: dict[str, Any]) -> dict[str, Any]:
    """The report without the error series only the figures use."""
    for r in robots.values():
        r.pop("_errors", None)
    return report


def hypothesis_errors(hyps: list[dict[str, Any]], own_frames: dict[str, np.ndarray]
                      ) -> list[dict[str, Any]]:
    """Each transform the maps suggested between two teams (see
    ``server.rendezvous.matchdesk``), its support, what became of it, and its error against
    the truth (team frames are their anchors' first poses); ``wrong``: beyond the false-merge
    bounds."""
    out = []
    for h in hyps:
        row: dict[str, Any] = {
            "sim_time_s": round(h["first_ns"] * 1e-9, 2), "last_s": round(h["last_ns"] * 1e-9, 2),
            "teams": [h["team_a"], h["team_b"]], "status": h["status"], "reason": h["reason"],
            "support": h["support"], "sides": [h["side_a"], h["side_b"]], "rival": h["rival"],
            "acceptance": h["acceptance"], "seen": h["seen"],
            "union_coverage": h.get("union_coverage"), "error_m": None,
            "error_deg": None, "wrong": None}
        a, b = h["anchor_a"], h["anchor_b"]
        if a in own_frames and b in own_frames:
            et, er = _transform_error(h["T_ab"], compose(inverse(own_frames[a]), own_frames[b]))
            row["error_m"], row["error_deg"] = round(et, 3), round(math.degrees(er), 2)
            row["wrong"] = et > FALSE_MERGE_M or er > FALSE_MERGE_RAD
        out.append(row)
    return out


def is_false_merge(row: dict[str, Any]) -> bool:
    """A merge row's verdict; reports written before the key was named ``false_merge`` called
    it ``"false"``."""
    return bool(row.get("false_merge", row.get("false", False)))


def write_truth_tum(truth: dict[str, Any], out_dir: Path) -> list[Path]:
    """Each robot's true trajectory in TUM format (``<id>_truth.tum``), to hold the server's
    ``trajectories/*.tum`` against with evo (docs/evo.md)."""
    from server.runtime.outputs import write_tum

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for rid, t in sorted(truth.items()):
        path = out_dir / f"{rid}_truth.tum"
        write_tum(path, t["stamps_ns"], t["poses"])
        paths.append(path)
    return paths


#: what the report takes from the server's summary per robot as it is
SERVER_ROBOT_FIELDS = ("scans", "keyframes", "loop_closures", "decisions",
                       "decision_ms_median", "mode")


def _truth_row(t: dict[str, Any], watch: dict[str, Any], rid: str) -> dict[str, Any]:
    """A robot's figures that need no server: the simulator's and the bus's."""
    return {"distance_m": round(t["distance_m"], 3), "collisions": t["collisions"],
            "bytes_sent": watch.get("bytes_sent", {}).get(rid, 0),
            "messages_sent": watch.get("messages_sent", {}).get(rid, 0)}


def print_summary(report: dict[str, Any], console: Any) -> None:
    from rich.table import Table

    if report["reached"]:
        outcome = (f"reached {report['threshold']:.0%} in "
                   f"{report['sim_time_to_threshold_s']:.0f} s sim")
    else:  # name the teams that fell short: a robot may never have met the others
        short = ", ".join(f"{tid} ({'+'.join(t['robot_ids'])}) {t['coverage'] or 0.0:.0%}"
                          for tid, t in report["teams"].items()
                          if not t.get("merged_into") and not t["reached"])
        outcome = (f"did NOT reach {report['threshold']:.0%} in {report['sim_time_s']:.0f} s "
                   f"sim: {short or 'no team known (no server outputs)'}")
    table = Table(title=f"{report['scenario']}: {outcome} ({report['wall_time_s']:.0f} s wall)")
    for col in ("robot", "distance m", "max pos err m", "max yaw err rad", "ATE m",
                "collisions", "bytes sent"):
        table.add_column(col)
    for rid, r in report["robots"].items():
        table.add_row(rid, f"{r['distance_m']:.1f}", str(r["max_position_error_m"]),
                      str(r["max_yaw_error_rad"]), str(r["ate_rmse_m"]), str(r["collisions"]),
                      f"{r['bytes_sent']:,}")
    console.print(table)
    console.print(f"true coverage {report['true_coverage']}, phantom area "
                  f"{report['phantom_area_m2']:.2f} m², end: {report['end']}")
    for r in report.get("server_restarts", []):
        how = r["signal"] or f"exit code {r['exit_code']}"
        then = (f"restarted after {r['back_off_s']:g} s, first command "
                f"{r.get('first_command_after_s')} s later" if r["restarted"]
                else "not restarted (no restarts left)" if r.get("back_off_s") is None
                else "not restarted (the run ended first)")
        console.print(f"[yellow]server died ({how}) at {r['wall_time_s']:.0f} s wall, "
                      f"{r['sim_time_s'] or 0.0:.0f} s sim: {then}[/]")
    if report.get("missing"):
        console.print("[yellow]missing or damaged, left out of the report:[/] "
                      + "; ".join(report["missing"]))
