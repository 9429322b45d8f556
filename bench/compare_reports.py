"""Compare two demo reports (``report.json``) field by field; print JSON.

Two lockstep runs with the same ``--seed`` should agree on everything the robots did; this
lists the fields where they do not, leaving out those that depend on the wall clock (times
measured on the machine, how long the processes ran on after the finish) and on paths.

    python bench/compare_reports.py RUN_A/report.json RUN_B/report.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

#: fields that vary with the machine's timing, not with what the robots did
WALL_CLOCK = {"wall_time_s", "decision_ms_median", "map_query_ms_median", "bytes_sent",
              "messages_sent", "scans",
              "sim_time_s", "exit_codes", "figures", "world"}


#: counters the server keeps counting until its process stops, a little after the finish: the
#: steps run meanwhile follow the machine's timing (case 2 seed 0, four runs: 75.1, 75.4, 75.5
#: and 75.6 s of simulated time at the end gave 109, 115, 115 and 118 tag sightings, all
#: finishing at 74.0 s). Their differences are listed apart and count against ``identical``
#: only where both runs ended at the same simulated time.
AFTER_FINISH = {"tag_counters"}


def differences(a: Any, b: Any, path: str = "") -> list[dict[str, Any]]:
    """The leaves where ``a`` and ``b`` differ (lists of unequal length count as one)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in WALL_CLOCK:
                out += differences(a.get(k), b.get(k), f"{path}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True))
                for d in differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [{"field": path, "a": a, "b": b}]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    a, b = (json.loads(p.read_text()) for p in (args.a, args.b))
    found = differences(a, b)
    late = [d for d in found if d["field"].split(".")[1].split("[")[0] in AFTER_FINISH]
    if a.get("sim_time_s") == b.get("sim_time_s"):
        late = []
    diffs = [d for d in found if d not in late]
    json.dump({"a": str(args.a), "b": str(args.b), "identical": not diffs,
               "differences": diffs, "counted_after_the_finish": late,
               "sim_time_s": [a.get("sim_time_s"), b.get("sim_time_s")]},
              sys.stdout, indent=1, default=str)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
