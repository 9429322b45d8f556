"""What a server run leaves behind: team maps (nav2 + PLY), trajectories and a summary.

Written while the server runs (every ``outputs_period_s``) and at shutdown; each file is
replaced whole (written beside, flushed to disk, renamed over), so a crash at any moment
leaves the previous good file, never half of one.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas import nav2map
from schemas.se2 import wrap_angle
from server.core import ServerCore
from server.planning import OccupancyGrid as PlanningGrid
from server.slam.export import write_ply
from server.slam.keyframes import Keyframe
from server.slam.mapping import point_cloud

#: the share of one core that rewriting the outputs may take
OUTPUTS_CPU_SHARE = 0.04
#: while a round is written, the share of its wall time the outputs' thread may be busy
OUTPUTS_DUTY = 0.2

#: what a round of writing calls between its files (``Spread``)
Pause = Callable[[], None]


def no_pause() -> None:
    """A round written at full speed (the last one, when the server stops)."""


class Spread:
    """The pauses that spread a round of writing over time (``Outputs.write`` calls this
    between a team's files, a robot's trajectories and the summary). After each piece it
    waits ``1 / duty - 1`` times as long as the piece took, so the outputs' thread is busy
    at most ``duty`` of the round's wall time, in stretches of one piece. ``stop`` ends the
    pauses (a server that stops writes on at full speed).

    The worker needs the interpreter (the GIL) for every scan. A round written in one go (at
    60 robots about 0.5 s of CPU after a minute, more as the trajectories grow: opening,
    writing and syncing 420 files, formatting trajectories) held it long enough that every
    robot's answers waited: 100–840 ms for one to three seconds after each round. Spread,
    the rounds alone left no answer over 100 ms (``docs/scale.md``)."""

    def __init__(self, duty: float = OUTPUTS_DUTY) -> None:
        self.factor = 1.0 / duty - 1.0
        self._stop = threading.Event()
        self._since: float | None = None

    def begin(self) -> None:
        """A round starts: its first piece is timed from now."""
        self._since = time.monotonic()

    def __call__(self) -> None:
        if self._since is not None:
            self._stop.wait((time.monotonic() - self._since) * self.factor)
        self._since = time.monotonic()

    def stop(self) -> None:
        self._stop.set()


class OutputPacer:
    """When the next outputs are due: every ``period_s``, or less often once a round (the
    gathering on the worker and the writing on the writer thread) costs more than
    ``OUTPUTS_CPU_SHARE`` of a core over its interval. The trajectories hold every scan's pose
    and are written whole, so a round grows with the mission: about 0.4 s of CPU per robot
    and hour of scans at 10 Hz (0.16 s for the CSV, 0.22 s for the TUM file of 36,000 poses),
    twice (online and final). Twenty robots after an hour would otherwise spend 15 s of CPU
    every 10 s on it; paced, they write every 6 minutes or so, and always at the end."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.gather_cpu_s = 0.0     # the last round's, on the worker
        self.write_cpu_s = 0.0      # the last round's, on the writer thread

    def next_in(self) -> float:
        """Seconds to the next round, from the last one's start."""
        return max(self.period_s, (self.gather_cpu_s + self.write_cpu_s) / OUTPUTS_CPU_SHARE)

    def timed_write(self, write: Callable[[], None]) -> Callable[[], None]:
        """``write``, its thread's CPU time kept as the round's writing cost."""
        def job() -> None:
            t0 = time.thread_time()
            try:
                write()
            finally:
                self.write_cpu_s = time.thread_time() - t0
        return job


@contextmanager
def replaced(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write; then flushed to disk and renamed over it."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_nav2_grid(grid: PlanningGrid, out_dir: Path, name: str = "map") -> Path:
    """nav2 map_server files (trinary PNG and YAML, ``schemas.nav2map``) of an int8 grid."""
    return nav2map.write(out_dir, name, grid.free, grid.occupied, grid.resolution_m,
                         grid.origin_xy)


def write_trajectory(path: Path, stamps_ns: Any, poses: Any) -> None:
    rows = np.column_stack([np.asarray(stamps_ns, np.int64).astype(object),
                            np.asarray(poses, np.float64).reshape(-1, 3)])
    with replaced(path) as tmp, tmp.open("w") as f:
        f.write("stamp_ns,x_m,y_m,theta_rad\n")
        for s, x, y, t in rows:
            f.write(f"{int(s)},{x:.5f},{y:.5f},{t:.6f}\n")


def tum_lines(stamps_ns: Any, poses: Any) -> str:
    """Planar poses as TUM trajectory lines, ``timestamp x y z qx qy qz qw`` (the format evo
    reads): the stamp in seconds, z = 0, the yaw as a rotation about z."""
    stamps = np.asarray(stamps_ns, np.int64)
    p = np.asarray(poses, np.float64).reshape(-1, 3)
    half = np.asarray(wrap_angle(p[:, 2])) / 2.0
    return "".join(f"{s // 10**9}.{s % 10**9:09d} {x:.5f} {y:.5f} 0 0 0 {qz:.7f} {qw:.7f}\n"
                   for s, x, y, qz, qw in zip(stamps.tolist(), p[:, 0], p[:, 1],
                                              np.sin(half), np.cos(half), strict=True))


def write_tum(path: Path, stamps_ns: Any, poses: Any) -> None:
    """A trajectory in TUM format (``tum_lines``), e.g. for ``evo_ape tum``."""
    with replaced(path) as tmp:
        tmp.write_text(tum_lines(stamps_ns, poses))


@dataclass
class Outputs:
    """What a server run writes, gathered from the core (copies, so another thread may write
    them while the core goes on)."""

    grids: dict[str, PlanningGrid]
    #: each team's point cloud, made when written: a long mission's keyframes hold millions of
    #: returns, and thinning them took the worker seconds (it holds the keyframes as they were
    #: and copies of their poses; keyframe scans never change)
    clouds: dict[str, Callable[[], NDArray[np.float64]]]
    trajectories: dict[str, tuple[list[int] | NDArray[np.int64], NDArray[np.float64]]]
    summary: dict[str, Any]

    def write(self, out_dir: Path, pause: Pause = no_pause) -> Path:
        """Write everything under ``out_dir``, calling ``pause`` between a team's files,
        each trajectory's and the summary (``Spread``); returns the summary's path."""
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "trajectories").mkdir(exist_ok=True)
        for team_id, grid in self.grids.items():
            tdir = out_dir / "maps" / team_id
            write_nav2_grid(grid, tdir)
            with replaced(tdir / "points.ply") as tmp:
                write_ply(tmp, self.clouds[team_id]())
            pause()
        for team_id in self.summary.get("merged_teams", {}):
            if team_id not in self.grids:   # its last map, in a team frame that is gone
                shutil.rmtree(out_dir / "maps" / team_id, ignore_errors=True)
        for name, (stamps, poses) in self.trajectories.items():
            write_trajectory(out_dir / "trajectories" / f"{name}.csv", stamps, poses)
            write_tum(out_dir / "trajectories" / f"{name}.tum", stamps, poses)
            pause()
        path = out_dir / "summary.json"
        with replaced(path) as tmp:
            tmp.write_text(json.dumps(self.summary, indent=2))
        return path


def _cloud(parts: list[tuple[tuple[Keyframe, ...], NDArray[np.float64]]]
           ) -> NDArray[np.float64]:
    """A team's point cloud from its robots' keyframes and their poses."""
    return np.concatenate([point_cloud(kfs, poses) for kfs, poses in parts])


def write_outputs(core: ServerCore, out_dir: Path, extra: dict[str, Any] | None = None) -> Path:
    """Write everything under ``out_dir``; returns the summary's path."""
    return collect_outputs(core, extra).write(out_dir)


def collect_outputs(core: ServerCore, extra: dict[str, Any] | None = None) -> Outputs:
    """Team maps and point clouds, trajectories and the summary, as of now."""
    grids: dict[str, PlanningGrid] = {}
    clouds: dict[str, Callable[[], NDArray[np.float64]]] = {}
    for team in core.teams.values():
        grids[team.team_id] = core.planning_grid(team.team_id)
        clouds[team.team_id] = functools.partial(_cloud, [
            (tuple(core.robots[r].slam.keyframes), core.robots[r].slam.keyframe_poses().copy())
            for r in team.robot_ids])
    trajectories: dict[str, tuple[list[int] | NDArray[np.int64], NDArray[np.float64]]] = {}
    robots: dict[str, Any] = {}
    for rid, r in core.robots.items():
        trajectories[f"{rid}_online"] = (r.online.stamps.copy(), r.online.values.copy())
        for first, rows in r.online_in.items():
            trajectories[f"{rid}_online_in_{first}"] = (rows.stamps.copy(), rows.values.copy())
        stamps, poses = r.slam.scan_poses()
        trajectories[f"{rid}_final"] = (np.array(stamps), np.array(poses))
        ms = r.nav.stats.decision_ms
        robots[rid] = {
            "team_id": r.team_id, "scans": r.scans, "late_scans": r.late_scans,
            "keyframes": len(r.slam.keyframes), "keyframes_reused": r.slam.stats.reused,
            "loop_closures": r.slam.stats.loop_closures, "distance_m": r.distance_m,
            "mode": r.nav.mode, "finished_reason": r.nav.finished_reason,
            "decisions": r.nav.stats.decisions, "targets_reached": r.nav.stats.targets_reached,
            "recoveries": r.nav.stats.recoveries, "looks": r.look.looks,
            "approaches": r.look.approaches, "calls": r.look.calls,
            "calls_unseen": r.look.calls_unseen,
            "decision_ms_median": float(np.median(ms)) if ms else None,
            "matches": dict(r.slam.stats.matches),
        }
    summary = {
        "robots": robots,
        "teams": {t.team_id: {"robot_ids": list(t.robot_ids), "coverage": t.coverage,
                              "explored_m2": t.explored_m2, "finished": t.finished,
                              "finished_stamp_ns": t.finished_stamp_ns,
                              "coverage_history": list(t.history)}
                  for t in core.teams.values()},
        "merged_teams": {t.team_id: {"merged_into": t.merged_into,
                                     "robot_ids": list(t.robot_ids),
                                     "coverage_history": list(t.history)}
                         for t in core.retired_teams.values()},
        "merges": [{"stamp_ns": m.stamp_ns, "team_id": m.team_id,
                    "joined_team_id": m.joined_team_id, "robots_a": list(m.robots_a),
                    "robots_b": list(m.robots_b), "sightings": m.sightings,
                    "T_joint": m.T_joint.tolist(), "T_fused": m.T_fused.tolist(),
                    "cov_fused": m.cov_fused.tolist(), "T_direct_first": m.T_direct_first.tolist(),
                    "map_agreement": m.agreement, "undone_stamp_ns": m.undone_stamp_ns,
                    "kind": m.kind}
                   for m in core.merges],
        "tag_counters": core.tag_counters,
        "map_hypotheses": core.matcher.hypotheses(),
        "map_query_ms": [round(v, 2) for v in core.matcher.query_ms],
        "events": [{"kind": e.kind, "stamp_ns": e.stamp_ns, "robot_ids": list(e.robot_ids),
                    "team_id": e.team_id, "message": e.message,
                    **({"figures": dict(e.figures)} if e.figures else {})}
                   for e in core.event_log],
        **(extra or {}),
    }
    return Outputs(grids, clouds, trajectories, summary)
