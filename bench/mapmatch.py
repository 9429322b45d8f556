"""Map matching between teams: time per query and what it finds; prints JSON.

Maps are scanned (ray-cast) from free places of boxes of a world, in each robot's own frame
(``bench/support/scanned.py``), so that the truth is known exactly. Pairs whose boxes overlap
must be accepted near the true transform; pairs whose boxes do not must never be. A query is
one submap matched against the other team's whole map (what the server's period costs per
place); a pair is every submap of both maps plus the consistency check.

    python bench/mapmatch.py [--world sim/worlds/large_house.world] [--pairs 12] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

from bench.support.scanned import box_pairs, scanned_map  # noqa: E402
from schemas.se2 import compose, inverse  # noqa: E402
from server.rendezvous.mapmatch import MatchParams, transform_error  # noqa: E402
from server.rendezvous.submaps import match_pair  # noqa: E402
from sim.loader import load_world  # noqa: E402
from sim.raycast import RayCaster  # noqa: E402

GOALS = {"query_ms_median": 200.0}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--world", type=Path, default=_HERE.parent / "sim/worlds/large_house.world")
    ap.add_argument("--pairs", type=int, default=12)
    ap.add_argument("--box", type=float, default=18.0, help="side of each robot's box [m]")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    w = load_world(a.world)
    caster = RayCaster(w.segments, w.circles)
    lo, hi = w.segments[:, :2].min(axis=0), w.segments[:, :2].max(axis=0)
    p = MatchParams()
    rows, query_ms, pair_ms = [], [], []
    for k, (ca, cb, Sa, Sb) in enumerate(box_pairs(lo, hi, a.box, a.pairs, a.seed)):
        ga, ka = scanned_map(caster, tuple(ca - a.box / 2), tuple(ca + a.box / 2), Sa, 2 * k)
        gb, kb = scanned_map(caster, tuple(cb - a.box / 2), tuple(cb + a.box / 2), Sb, 2 * k + 1)
        t0 = time.perf_counter()
        res = match_pair(ga, gb, ka, kb, p)
        pair_ms.append((time.perf_counter() - t0) * 1e3)
        query_ms += res.query_ms
        shared = float(np.prod(np.clip(a.box - np.abs(cb - ca), 0, None)))
        row = {"boxes_overlap_m2": round(shared, 1), "submaps": res.submaps,
               "candidates": len(res.candidates), "pair_ms": round(pair_ms[-1], 1)}
        if res.best is not None:
            et, er = transform_error(res.best.T_ab, compose(inverse(Sa), Sb))
            row.update(support=res.best.support, rival=res.best.rival_support,
                       sides=[res.best.side_support("a"), res.best.side_support("b")],
                       accepted=res.best.accepted(p), error_m=round(et, 3),
                       error_deg=round(math.degrees(er), 2))
        rows.append(row)
        print(json.dumps(row), file=sys.stderr)
    accepted = [r for r in rows if r.get("accepted")]
    wrong = [r for r in accepted if r["error_m"] > 0.5 or r["error_deg"] > 5.0]
    out = {
        "world": str(a.world), "pairs": len(rows), "box_m": a.box,
        "query_ms_median": round(float(np.median(query_ms)), 1) if query_ms else None,
        "query_ms_p90": round(float(np.percentile(query_ms, 90)), 1) if query_ms else None,
        "queries": len(query_ms),
        "pair_ms_median": round(float(np.median(pair_ms)), 1),
        "overlapping_pairs_accepted": sum(1 for r in accepted if r["boxes_overlap_m2"] > 0),
        "overlapping_pairs": sum(1 for r in rows if r["boxes_overlap_m2"] > 0),
        "accepted_wrong": len(wrong),
        "accepted_error_max_m": max((r["error_m"] for r in accepted), default=None),
        "rows": rows, "goals": GOALS,
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
