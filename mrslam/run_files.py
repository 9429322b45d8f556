"""Readers of a demo run's files, shared by the report and its figures: the simulator's
ground truth (``sim/truth.jsonl``) and the server's trajectories (``trajectories/*.csv``, as
``server.outputs`` writes them)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def read_truth(path: Path) -> dict[str, dict[str, Any]]:
    """Per robot: stamps_ns, poses (N, 3), and the last collisions / distance counters."""
    rows: dict[str, dict[str, list[Any]]] = {}
    last: dict[str, dict[str, Any]] = {}
    with path.open() as f:
        for line in f:
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short when the simulator was stopped
            for p in rec.get("poses", []):
                r = rows.setdefault(p["robot_id"], {"stamps": [], "poses": []})
                r["stamps"].append(rec["stamp_ns"])
                r["poses"].append(p["pose"])
                last[p["robot_id"]] = p
    return {rid: {"stamps_ns": np.asarray(r["stamps"], np.int64),
                  "poses": np.asarray(r["poses"], np.float64).reshape(-1, 3),
                  "collisions": int(last[rid].get("collisions", 0)),
                  "distance_m": float(last[rid].get("distance_m", 0.0))}
            for rid, r in rows.items()}


def read_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """stamps_ns (N,) and poses (N, 3) of a trajectory CSV (``stamp_ns,x_m,y_m,theta_rad`` rows)."""
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.size == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    return data[:, 0].astype(np.int64), data[:, 1:4]
