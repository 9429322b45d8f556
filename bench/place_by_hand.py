"""Placing robots by hand on a known map: how often a rough pose is refined and placed right,
how often a wrong one is refused, and how long the order takes. Prints JSON.

Per seed: one robot at a random free pose in ``--world`` (the map surveyed from the truth,
``bench.support.survey``), never placed by itself (confirmations out of reach; with
``--by-itself`` the server's own search goes on, and a run it places first has no order); after
``--after`` simulated seconds, the order ``place`` with its true pose put off by ``--off-m``
in a random direction and ``--off-deg`` (as a press and drag on a screen), after one with its
pose ``--wrong-m`` off (somewhere else in the house), which must be refused. Among rooms
alike (the ambiguous wings) the rough pose is refused too while nothing the robot has seen
tells the rooms apart (``refused_alike``). The placed
robot's error against the truth is taken when placed and ``--settle`` simulated seconds later.

    PYTHONPATH=$PWD .venv/bin/python -m bench.place_by_hand --seeds 5
    PYTHONPATH=$PWD .venv/bin/python -m bench.place_by_hand --world ambiguous_wings --by-itself
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

import numpy as np

from bench.support.known_mission import WORLDS, demo_config, free_poses, mission
from bench.support.survey import survey_map
from server.command.operator import parse
from server.knownmap.ghosts import MAP_TEAM


def one(seed: int, a: argparse.Namespace) -> dict[str, Any]:
    world = WORLDS / f"{a.world}.world"
    rng = np.random.default_rng(seed)
    m = mission(world, survey_map(world, spacing_m=1.5),
                {"r1": free_poses(world, 1, rng)[0]},
                demo_config(**({} if a.by_itself else {"confirmations": 10**6,
                                                       "query_period_s": 10**6})),
                np.zeros(3), seed=seed)
    m.run_until(a.after, done=lambda k: k.core.robots.get("r1") is not None
                and k.core.robots["r1"].team_id == MAP_TEAM)
    if m.core.robots["r1"].team_id == MAP_TEAM:
        return {"seed": seed, "placed_by_itself": True}
    truth = np.array(m.sim.robots["r1"].pose, float)

    def place(pose: np.ndarray, stamp: int) -> tuple[int, str, float]:
        t0 = time.perf_counter()
        status, line = m.core.operate(parse({"action": "place", "robot_id": "r1",
                                             "pose": [float(v) for v in pose]}), stamp)
        return status, line, (time.perf_counter() - t0) * 1e3

    d = rng.uniform(-math.pi, math.pi)
    wrong = truth + np.array([a.wrong_m * math.cos(d), a.wrong_m * math.sin(d), 0.0])
    w_status, w_line, w_ms = place(wrong, 1)
    wrongly = m.core.robots["r1"].team_id == MAP_TEAM
    d = rng.uniform(-math.pi, math.pi)
    rough = truth + np.array([a.off_m * math.cos(d), a.off_m * math.sin(d),
                              math.radians(a.off_deg) * rng.choice([-1, 1])])
    status, line, ms = place(rough, 2)
    placed = m.core.robots["r1"].team_id == MAP_TEAM
    err_m, err_deg = m.error("r1") if placed else (None, None)
    m.run_until(m.sim_time_s + a.settle)
    later = m.error("r1") if m.core.robots["r1"].team_id == MAP_TEAM else (None, None)
    return {"seed": seed, "wrong_refused": w_status == 409 and not wrongly,
            "wrong_answer": w_line, "wrong_ms": round(w_ms, 1),
            "placed": placed and status == 200, "answer": line, "ms": round(ms, 1),
            "refused_alike": status == 409 and "tells them apart" in line,
            "error_m": None if err_m is None else round(err_m, 4),
            "error_deg": None if err_deg is None else round(err_deg, 3),
            "later_error_m": None if later[0] is None else round(later[0], 4),
            "later_error_deg": None if later[1] is None else round(later[1], 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--world", default="small_house", help="small_house, ambiguous_wings, …")
    ap.add_argument("--by-itself", action="store_true",
                    help="the server's own search goes on too (runs it placed first are "
                    "counted as placed_by_itself, with no order)")
    ap.add_argument("--after", type=float, default=3.0, help="simulated s before the orders")
    ap.add_argument("--off-m", type=float, default=0.5)
    ap.add_argument("--off-deg", type=float, default=12.0)
    ap.add_argument("--wrong-m", type=float, default=3.0)
    ap.add_argument("--settle", type=float, default=3.0,
                    help="simulated s run after the placement, then the error again")
    a = ap.parse_args()
    runs = [one(s, a) for s in range(a.seeds)]
    ordered = [r for r in runs if not r.get("placed_by_itself")]
    good = [r for r in ordered if r["placed"]]
    print(json.dumps({
        "runs": runs, "world": a.world, "placed_by_itself": len(runs) - len(ordered),
        "placed": len(good), "of": len(ordered),
        "refused_alike": sum(r["refused_alike"] for r in ordered),
        "wrong_refused": sum(r["wrong_refused"] for r in ordered),
        "worst_error_m": max((r["error_m"] for r in good), default=None),
        "worst_error_deg": max((r["error_deg"] for r in good), default=None),
        "worst_later_error_m": max((r["later_error_m"] or math.inf for r in good),
                                   default=None),
        "worst_later_error_deg": max((r["later_error_deg"] or math.inf for r in good),
                                     default=None),
        "order_ms_max": max((max(r["ms"], r["wrong_ms"]) for r in ordered), default=None)},
        indent=1))


if __name__ == "__main__":
    main()
