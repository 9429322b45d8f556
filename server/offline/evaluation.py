"""Relation-based accuracy of a trajectory (Kümmerle et al., "On measuring the accuracy of SLAM
algorithms", Autonomous Robots 27(4), 2009).

For a reference relation (t1, t2, δ*) and estimated poses x_t1, x_t2 the error is
``ε = δ* ⊖ (x_t1⁻¹ ⊕ x_t2)``; the score is the mean ± std of its absolute translational [m] and
rotational [deg] parts over all relations whose two stamps match an estimated pose.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, inverse

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
DEFAULT_TOLERANCE_S = 0.005


class EvaluationError(Exception):
    """A poses or relations file is missing, unreadable or has no usable lines."""

    user_error = True


@dataclass(frozen=True)
class RelationErrors:
    """Summary of the relation errors; ``unmatched`` relations had a stamp without a pose."""

    trans_mean_m: float
    trans_std_m: float
    rot_mean_deg: float
    rot_std_deg: float
    matched: int
    unmatched: int
    relations: int
    poses: int
    skipped_lines: int


def _read_table(path: Path, n_cols: int, what: str) -> tuple[F64, int]:
    """Rows of the first ``n_cols`` numbers per line; comments and blank lines are ignored,
    bad lines counted."""
    try:
        text = path.read_text(encoding="ascii", errors="replace")
    except FileNotFoundError:
        raise EvaluationError(f"{path}: no such {what} file") from None
    except (IsADirectoryError, PermissionError) as e:
        raise EvaluationError(f"{path}: cannot read {what} file ({e.strerror})") from None
    rows: list[list[float]] = []
    bad = 0
    for line in text.splitlines():
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        try:
            vals = [float(w) for w in words[:n_cols]]
        except ValueError:
            bad += 1
            continue
        if len(vals) < n_cols or not all(math.isfinite(v) for v in vals):
            bad += 1
            continue
        rows.append(vals)
    if not rows:
        raise EvaluationError(f"{path}: no usable lines in {what} file")
    return np.asarray(rows, dtype=np.float64), bad


def read_poses(path: Path) -> tuple[F64, F64, int]:
    """``timestamp x y theta`` lines → stamps [s] (sorted), poses (N, 3), skipped line count."""
    table, bad = _read_table(path, 4, "poses")
    order = np.argsort(table[:, 0], kind="stable")
    return table[order, 0], table[order, 1:4], bad


def read_relations(path: Path) -> tuple[F64, F64, F64, int]:
    """``t1 t2 x y z roll pitch yaw`` lines → t1, t2 [s], planar δ* (N, 3), skipped count."""
    table, bad = _read_table(path, 8, "relations")
    return table[:, 0], table[:, 1], table[:, [2, 3, 7]], bad


def match_stamps(stamps: F64, queries: F64, tolerance_s: float) -> NDArray[np.int64]:
    """Index of the nearest stamp to each query, or −1 if none lies within ``tolerance_s``."""
    j = np.clip(np.searchsorted(stamps, queries), 1, max(len(stamps) - 1, 1))
    left = np.clip(j - 1, 0, len(stamps) - 1)
    right = np.clip(j, 0, len(stamps) - 1)
    pick = np.where(np.abs(stamps[left] - queries) <= np.abs(stamps[right] - queries), left, right)
    ok = np.abs(stamps[pick] - queries) <= tolerance_s
    return np.where(ok, pick, -1).astype(np.int64)


def relation_errors(poses_a: F64, poses_b: F64, delta_ref: F64) -> tuple[F64, F64]:
    """Per relation: |trans(ε)| [m] and |rot(ε)| [rad] of ε = δ* ⊖ (x_a⁻¹ ⊕ x_b)."""
    delta_est = between(poses_a, poses_b)
    eps = compose(inverse(delta_est), delta_ref)  # δ* ⊖ δ = δ⁻¹ ⊕ δ*
    return np.hypot(eps[:, 0], eps[:, 1]), np.abs(eps[:, 2])


def evaluate(poses_path: Path, relations_path: Path,
             tolerance_s: float = DEFAULT_TOLERANCE_S) -> RelationErrors:
    stamps, poses, bad_p = read_poses(Path(poses_path))
    t1, t2, delta, bad_r = read_relations(Path(relations_path))
    i1 = match_stamps(stamps, t1, tolerance_s)
    i2 = match_stamps(stamps, t2, tolerance_s)
    ok = (i1 >= 0) & (i2 >= 0)
    n = int(ok.sum())
    if n == 0:
        raise EvaluationError(f"no relation of {relations_path} matched a pose of {poses_path} "
                              f"within {tolerance_s} s")
    e_t, e_r = relation_errors(poses[i1[ok]], poses[i2[ok]], delta[ok])
    e_deg = np.degrees(e_r)
    return RelationErrors(float(e_t.mean()), float(e_t.std()), float(e_deg.mean()),
                          float(e_deg.std()), n, int((~ok).sum()), len(t1), len(stamps),
                          bad_p + bad_r)


def run(poses: Path, relations: Path, tolerance_s: float = DEFAULT_TOLERANCE_S,
        as_json: bool = False) -> RelationErrors:
    """Score ``poses`` against ``relations`` and print the result (a table, or JSON)."""
    res = evaluate(poses, relations, tolerance_s)
    if as_json:
        print(json.dumps(asdict(res)))
        return res
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"relations: {Path(relations).name}")
    table.add_column("error")
    table.add_column("mean ± std", justify="right")
    table.add_row("translational [m]", f"{res.trans_mean_m:.4f} ± {res.trans_std_m:.4f}")
    table.add_row("rotational [deg]", f"{res.rot_mean_deg:.3f} ± {res.rot_std_deg:.3f}")
    table.add_row("relations matched", f"{res.matched} / {res.relations}")
    table.add_row("unmatched", str(res.unmatched))
    if res.skipped_lines:
        table.add_row("unreadable lines", str(res.skipped_lines))
    Console().print(table)
    return res
