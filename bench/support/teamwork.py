"""Whether a team's robots pay their way, from one demo run's outputs (``bench/multi.py``).

- ``flat_stretches``: the stretches in which a team's coverage stays flat while its robots
  drive (the issue's goal: none longer than 20 s). A team's coverage comes from its own
  history (a sample a second, ``report.json``); which robots were in it when, from the
  run's merges; how far each drove, from the simulator's truth (``sim/truth.jsonl``).
- ``detour_pairs``: each detour the server priced (``detour`` events, ``server.fleet.detours``)
  with its outcome: the saving estimated when it was decided and the one measured when it
  was settled.
- ``correlation``: how well those estimates agree with the outcomes over many runs.
- ``team_vs_alone``: a team's time against its fastest member's alone on the same seed.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

#: coverage that grows by less than this much area [m²] is flat
FLAT_M2 = 1.0
#: a stretch counts when the team's robots drove at least this far in it, together [m]
DRIVING_M = 1.0
#: the kinds of detour whose outcome is a merge (the others are settled otherwise)
MERGE_KINDS = ("seek", "call", "meeting")


def distances(truth_path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each robot's distance driven over sim time, (t [s], d [m]), from the simulator's truth
    log; empty when the log is missing or unreadable."""
    ts: dict[str, list[float]] = {}
    ds: dict[str, list[float]] = {}
    try:
        with truth_path.open() as f:
            for line in f:
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                t = float(rec.get("stamp_ns", 0)) * 1e-9
                for p in rec.get("poses", ()):
                    ts.setdefault(p["robot_id"], []).append(t)
                    ds.setdefault(p["robot_id"], []).append(float(p.get("distance_m", 0.0)))
    except OSError:
        return {}
    return {r: (np.asarray(ts[r]), np.asarray(ds[r])) for r in ts}


def members(team_id: str, team: dict[str, Any], merges: list[dict[str, Any]]
            ) -> list[tuple[float, set[str]]]:
    """The team's robots over time: (from when [s], which robots), from its merges."""
    first = team_id.removeprefix("team-")
    start = {first} if first in team.get("robot_ids", ()) else set(team.get("robot_ids", ()))
    out = [(0.0, start)]
    for m in sorted((m for m in merges if not m.get("undone")),
                    key=lambda m: float(m.get("sim_time_s") or 0.0)):
        if m.get("team_id") == team_id:
            out.append((float(m["sim_time_s"]), set(m.get("robots", ())) | out[-1][1]))
    return out


def _robots_at(span: list[tuple[float, set[str]]], t: float) -> set[str]:
    now = span[0][1]
    for since, robots in span:
        if since <= t:
            now = robots
    return now


def flat_stretches(report: dict[str, Any], truth: dict[str, tuple[np.ndarray, np.ndarray]]
                   ) -> dict[str, Any]:
    """The longest stretch of each team's flat coverage in which its robots drove, and the
    run's longest over its teams: {"longest_s", "team", "from_s", "to_s", "driven_m",
    "teams": {team: {...}}}. A team's stretches end where it reached its threshold or was
    merged into another."""
    area = float(report.get("area_m2") or 0.0)
    eps = FLAT_M2 / area if area > 0 else 1e-3
    merges = report.get("merges") or []
    teams_out: dict[str, Any] = {}
    for tid, team in (report.get("teams") or {}).items():
        hist = np.asarray(team.get("coverage_history") or [], dtype=float).reshape(-1, 2)
        if len(hist) < 2:
            continue
        end = team.get("sim_time_to_threshold_s")
        if end is not None:
            hist = hist[hist[:, 0] <= float(end) + 1e-6]
        span = members(tid, team, merges)
        best: dict[str, Any] = {"longest_s": 0.0, "from_s": None, "to_s": None, "driven_m": 0.0}
        t, c = hist[:, 0], hist[:, 1]
        i = 0
        while i < len(t) - 1:
            k = i + 1
            while k < len(t) and c[k] <= c[i] + eps:
                k += 1
            t1 = t[k - 1]    # the last sample still flat
            if t1 - t[i] > best["longest_s"]:
                driven = sum(float(np.interp(t1, *truth[r]) - np.interp(t[i], *truth[r]))
                             for r in _robots_at(span, float(t[i])) if r in truth)
                if driven >= DRIVING_M:
                    best = {"longest_s": round(float(t1 - t[i]), 1),
                            "from_s": round(float(t[i]), 1), "to_s": round(float(t1), 1),
                            "driven_m": round(driven, 1)}
            i += 1
        teams_out[tid] = best
    worst = max(teams_out.items(), key=lambda kv: kv[1]["longest_s"], default=None)
    if worst is None:
        return {"longest_s": None, "team": None, "teams": {}}
    return {**worst[1], "team": worst[0], "teams": teams_out}


def detour_pairs(events: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every detour decided in the run: kind (from its message), its figures when decided
    and, once settled, the saving measured."""
    decided: dict[int, dict[str, Any]] = {}
    for e in events:
        if e.get("kind") != "detour" or "figures" not in e:
            continue
        f = e["figures"]
        ident = int(f.get("id", -1))
        if "taken" in f:
            kind = str(e.get("message", "")).split(" ", 1)[0].split(":", 1)[0]
            decided[ident] = {"id": ident, "kind": kind, "robots": e.get("robot_ids", []),
                              "t_s": round(float(e.get("stamp_ns", 0)) * 1e-9, 1),
                              **{k: f[k] for k in ("robot_s", "cost_s", "saving_s", "gain_s",
                                                   "p") if k in f},
                              "taken": bool(f["taken"]), "measured_s": None}
        elif "measured_s" in f and ident in decided:
            decided[ident]["measured_s"] = float(f["measured_s"])
            decided[ident]["after_s"] = float(f.get("after_s", 0.0))
    return list(decided.values())


def _pearson(x: np.ndarray, y: np.ndarray) -> float | None:
    if len(x) < 3 or np.std(x) == 0 or np.std(y) == 0:
        return None
    return round(float(np.corrcoef(x, y)[0, 1]), 3)


def _ranks(v: np.ndarray) -> np.ndarray:
    order = np.argsort(v, kind="stable")
    r = np.empty(len(v))
    r[order] = np.arange(len(v))
    for val in np.unique(v):      # ties share their mean rank
        same = v == val
        r[same] = r[same].mean()
    return r


def correlation(pairs: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """Estimated against measured savings of the settled detours, per kind and for the kinds
    a merge settles together: how many, Pearson's and Spearman's r, the means, and how often
    a detour estimated worth its cost measured more than its cost."""
    pairs = list(pairs)
    settled = [p for p in pairs if p.get("measured_s") is not None]
    out: dict[str, Any] = {}
    groups: dict[str, list[dict[str, Any]]] = {"merge_kinds": [
        p for p in settled if p["kind"] in MERGE_KINDS]}
    for p in settled:
        groups.setdefault(p["kind"], []).append(p)
    for name, ps in groups.items():
        x = np.asarray([p["saving_s"] for p in ps], dtype=float)
        y = np.asarray([p["measured_s"] for p in ps], dtype=float)
        cost = np.asarray([p.get("cost_s", 0.0) for p in ps], dtype=float)
        out[name] = {
            "n": len(ps),
            "pearson_r": _pearson(x, y),
            "spearman_r": _pearson(_ranks(x), _ranks(y)) if len(ps) >= 3 else None,
            "mean_estimated_s": round(float(x.mean()), 2) if len(ps) else None,
            "mean_measured_s": round(float(y.mean()), 2) if len(ps) else None,
            "paid": int((y > 0).sum()),
            "worth_and_paid": int(((x > cost) & (y > cost)).sum()),
            "worth_estimated": int((x > cost).sum()),
        }
    out["decided"] = len(pairs)
    out["declined"] = sum(1 for p in pairs if not p.get("taken"))
    return out


def team_vs_alone(team_s: float | None, alone_s: dict[str, float | None]) -> dict[str, Any]:
    """A team's time to threshold against each member's alone (those measured) on the same
    seed: the fastest member's time, the ratio and whether the team was no slower."""
    got = {r: t for r, t in alone_s.items() if t}
    if not team_s or not got:
        return {"team_s": team_s, "alone_s": alone_s, "fastest_alone_s": None,
                "speedup": None, "no_slower": None}
    fastest = min(got.values())
    return {"team_s": team_s, "alone_s": alone_s, "fastest_alone_s": fastest,
            "speedup": round(fastest / team_s, 3), "no_slower": team_s <= fastest}
