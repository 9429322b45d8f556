"""The run's figures: coverage vs time, pose error vs time, the map with trajectories."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mrslam.run_files import Gaps, read_trajectory


def write_figures(report: dict[str, Any], out: Path, gaps: Gaps) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written: list[str] = []
    fig, ax = plt.subplots(figsize=(7, 4))
    for team_id, team in report["teams"].items():
        h = np.asarray(team["coverage_history"], dtype=np.float64).reshape(-1, 2)
        ax.plot(h[:, 0], 100 * h[:, 1], label=f"{team_id} ({', '.join(team['robot_ids'])})")
    for ev in report.get("events", []):
        if ev["kind"] == "merge":
            ax.axvline(ev["stamp_ns"] * 1e-9, color="grey", ls=":", lw=1)
    ax.axhline(100 * report["threshold"], color="k", ls="--", lw=1, label="threshold")
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("coverage [%]")
    ax.set_title(f"{report['scenario']}: coverage")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "coverage.png", dpi=120)
    plt.close(fig)
    written.append("coverage.png")

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for rid, r in report["robots"].items():
        if "_errors" not in r:   # no online poses from the server
            continue
        t, pos, yaw = r["_errors"]
        ax1.plot(t, pos, label=rid)
        ax2.plot(t, np.degrees(yaw), label=rid)
    ax1.set_ylabel("position error [m]")
    ax2.set_ylabel("yaw error [deg]")
    ax2.set_xlabel("simulated time [s]")
    ax1.set_title(f"{report['scenario']}: online pose error vs ground truth")
    for a in (ax1, ax2):
        a.grid(alpha=0.3)
        if a.lines:
            a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "pose_error.png", dpi=120)
    plt.close(fig)
    written.append("pose_error.png")
    written += _maps(report, out, plt, gaps)
    return written


def _maps(report: dict[str, Any], out: Path, plt: Any, gaps: Gaps) -> list[str]:
    from schemas.occupancy import FREE_BELOW, OCCUPIED_ABOVE, UNKNOWN
    from sim.errors import WorldError
    from sim.grid import read_nav2

    written = []
    for team_id, team in report["teams"].items():
        yml = out / "server" / "maps" / team_id / "map.yaml"
        if not yml.exists():
            continue
        try:
            g = read_nav2(yml)
        except WorldError as e:
            gaps.note(yml, f"map not drawn: {e}")
            continue
        img = np.full(g.cells.shape, 0.8)
        img[(g.cells != UNKNOWN) & (g.cells < FREE_BELOW)] = 1.0
        img[g.cells > OCCUPIED_ABOVE] = 0.0
        h, w = g.cells.shape
        x0, y0 = g.origin[0], g.origin[1]
        extent = (x0, x0 + w * g.resolution_m, y0, y0 + h * g.resolution_m)
        fig, ax = plt.subplots(figsize=(7, 7))
        ax.imshow(img, cmap="gray", origin="lower", extent=extent, vmin=0, vmax=1)
        for rid in team["robot_ids"]:
            path = out / "server" / "trajectories" / f"{rid}_final.csv"
            if path.exists():
                _, poses = read_trajectory(path, gaps)
                ax.plot(poses[:, 0], poses[:, 1], lw=1, label=rid)
        ax.set_title(f"{team_id}: map and trajectories (map frame)")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(fontsize=8)
        fig.tight_layout()
        name = f"map_{team_id}.png"
        fig.savefig(out / name, dpi=120)
        plt.close(fig)
        written.append(name)
    return written
