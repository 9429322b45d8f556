"""A section of ``bench/hostile.py``: the server's state folder on a disk that fills up.

- ``full_disk``: the default demo (three robots, lockstep) with ``MRSLAM_STATE_DIR`` on a
  tmpfs of ``size_mb`` (3 MB by default), which the journal and snapshots fill within the
  first minute. Goal: the demo reaches its threshold with 0 false merges, and the state's
  failure is reported once (one log line) with its count (``summary.json``). Needs root to
  mount the tmpfs; says so otherwise.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any


def full_disk(folder: Path, size_mb: int = 3) -> dict[str, Any]:
    from mrslam.demo import run as demo

    state = folder / "state"
    state.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return {"skipped": "mounting a tmpfs needs root", "goal_met": None}
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(state)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        return {"skipped": f"cannot mount a tmpfs: {r.stderr.strip()}", "goal_met": None}
    old = os.environ.get("MRSLAM_STATE_DIR")
    os.environ["MRSLAM_STATE_DIR"] = str(state)
    try:
        report = demo({"out": str(folder / "run"), "record": False}, progress=False)
    finally:
        if old is None:
            os.environ.pop("MRSLAM_STATE_DIR", None)
        else:
            os.environ["MRSLAM_STATE_DIR"] = old
        subprocess.run(["umount", "-l", str(state)], check=False)
    run = folder / "run"
    summary = json.loads((run / "server" / "summary.json").read_text())
    journal = summary.get("journal") or {}
    log = (run / "logs" / "server.log").read_text(errors="replace")
    lines = [ln for ln in log.splitlines() if "state: writing the" in ln]
    best = max(report["teams"].values(), key=lambda t: t["coverage"])
    failures = sum((journal.get("failures") or {}).values())
    return {
        "tmpfs_mb": size_mb, "reached": best["reached"], "coverage": best["coverage"],
        "sim_time_to_threshold_s": best["sim_time_to_threshold_s"],
        "false_merges": int(report.get("false_merges", 0)), "end": report.get("end"),
        "state": {k: journal.get(k) for k in ("writing", "failures", "not_journaled",
                                              "resumed", "last_error", "entries")},
        "state_log_lines": lines[:5], "tracebacks": log.count("Traceback"),
        "goal_met": bool(best["reached"]) and not report.get("false_merges")
        and failures >= 1 and len(lines) == 1 and "Traceback" not in log,
    }


SECTIONS = {"full_disk": full_disk}
