"""Readers of a demo run's files, shared by the report and its figures: the simulator's
ground truth (``sim/truth.jsonl``), the server's summary and trajectories (``trajectories/*.csv``,
as ``server.runtime.outputs`` writes them).

A run may end without some of these (a server that died and could not be restarted leaves no
outputs, or only those of its last periodic refresh) or with a damaged one. Each reader then
returns what is intact (an empty result when nothing is) and notes what is wrong in ``Gaps``,
which the report lists under ``missing``: damage is reported, never fatal for the rest.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class Gaps:
    """What a run folder lacks or holds damaged: one line per file, its path relative to
    ``root``."""

    root: Path
    notes: list[str] = field(default_factory=list)

    def note(self, path: Path, what: str) -> None:
        try:
            name = str(path.relative_to(self.root))
        except ValueError:
            name = str(path)
        text = f"{name}: {what}"
        if text not in self.notes:
            self.notes.append(text)
            log.warning("%s", text)


def _read_bytes(path: Path, gaps: Gaps, missing: str) -> bytes | None:
    """The file's bytes; None (and a note: ``missing``, or why it cannot be read) otherwise."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        gaps.note(path, missing)
    except OSError as e:
        gaps.note(path, f"cannot read ({e.strerror})")
    return None


def read_json(path: Path, gaps: Gaps) -> dict[str, Any]:
    """A JSON object file; ``{}`` when it is missing, unreadable or not an object."""
    raw = _read_bytes(path, gaps, "missing")
    if raw is None:
        return {}
    try:
        data = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        gaps.note(path, f"not valid JSON, cut short or damaged ({e})")
        return {}
    if not isinstance(data, dict):
        gaps.note(path, f"expected a JSON object, found {type(data).__name__}")
        return {}
    return data


def read_truth(path: Path, gaps: Gaps) -> dict[str, dict[str, Any]]:
    """Per robot: stamps_ns, poses (N, 3), and the last collisions / distance counters.
    A last line cut short (the simulator stopped while writing) is normal; other lines that do
    not parse are skipped and noted."""
    rows: dict[str, dict[str, list[Any]]] = {}
    last: dict[str, dict[str, Any]] = {}
    raw = _read_bytes(path, gaps, "missing: no ground truth to score against")
    if raw is None:
        return {}
    lines = raw.splitlines()
    bad = 0
    for n, line in enumerate(lines):
        try:
            rec = json.loads(line)
            poses = [(p["robot_id"], rec["stamp_ns"], p["pose"], p) for p in rec.get("poses", [])]
        except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, AttributeError):
            bad += n < len(lines) - 1
            continue
        for rid, stamp, pose, p in poses:
            r = rows.setdefault(rid, {"stamps": [], "poses": []})
            r["stamps"].append(stamp)
            r["poses"].append(pose)
            last[rid] = p
    if bad:
        gaps.note(path, f"{bad} damaged line(s) skipped")
    return {rid: {"stamps_ns": np.asarray(r["stamps"], np.int64),
                  "poses": np.asarray(r["poses"], np.float64).reshape(-1, 3),
                  "collisions": int(last[rid].get("collisions", 0)),
                  "distance_m": float(last[rid].get("distance_m", 0.0))}
            for rid, r in rows.items()}


def read_trajectory(path: Path, gaps: Gaps) -> tuple[np.ndarray, np.ndarray]:
    """stamps_ns (N,) and poses (N, 3) of a trajectory CSV (``stamp_ns,x_m,y_m,theta_rad``
    rows); rows that do not hold four finite numbers are skipped and noted."""
    try:
        lines = path.read_text(errors="replace").splitlines()[1:]
    except FileNotFoundError:
        gaps.note(path, "missing")
        return np.zeros(0, np.int64), np.zeros((0, 3))
    except OSError as e:
        gaps.note(path, f"cannot read ({e.strerror})")
        return np.zeros(0, np.int64), np.zeros((0, 3))
    stamps: list[int] = []
    poses: list[tuple[float, float, float]] = []
    bad = 0
    for line in lines:
        cells = line.split(",")
        try:
            stamp, x, y, theta = int(float(cells[0])), *map(float, cells[1:4])
            if len(cells) != 4 or not all(map(math.isfinite, (x, y, theta))):
                raise ValueError(line)
        except (ValueError, IndexError, OverflowError):
            bad += 1
            continue
        stamps.append(stamp)
        poses.append((x, y, theta))
    if bad:
        gaps.note(path, f"{bad} damaged row(s) skipped")
    return np.asarray(stamps, np.int64), np.asarray(poses, np.float64).reshape(-1, 3)
