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
    capped = False
    joined = merge_times(report)
    for team_id, team in report["teams"].items():
        h = np.asarray(team["coverage_history"], dtype=np.float64).reshape(-1, 2)
        # the area measured can outgrow the nominal one (wall faces, a bent map): the plot
        # stops at 100 % and says so; report.json keeps the values as measured
        capped |= bool((h[:, 1] > 1.0).any())
        label = f"{team_id} ({', '.join(team['robot_ids'])})"
        if team.get("merged_into"):   # its curve ends where its robots joined another team
            at = joined.get(team_id)
            label += f", into {team['merged_into']}" + (f" at {at:.1f} s" if at else "")
        ax.plot(h[:, 0], 100 * np.minimum(h[:, 1], 1.0), label=label,
                lw=1.0 if team.get("merged_into") else 1.8)
    merged_at = [ev["stamp_ns"] * 1e-9 for ev in report.get("events", [])
                 if ev["kind"] == "merge"]
    for i, t in enumerate(merged_at):
        ax.axvline(t, color="grey", ls=":", lw=1, label="merge" if i == 0 else None)
    ax.axhline(100 * report["threshold"], color="k", ls="--", lw=1, label="threshold")
    ax.set_ylim(0, 105)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("coverage [%]" + (" (capped at 100)" if capped else ""))
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


def _map_key(plt: Any) -> list[Any]:
    """Legend entries for the markers and the map's shades."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    return [Line2D([], [], marker="o", ls="", color="k", mfc="white", mew=2, label="start"),
            Line2D([], [], marker="s", ls="", color="k", label="end"),
            Line2D([], [], marker="*", ls="", color="w", mec="k", ms=12, label="merge (meeting)"),
            Patch(fc="white", ec="k", label="free"), Patch(fc="black", label="occupied"),
            Patch(fc=str(0.8), ec="k", label="unknown")]


def merge_times(report: dict[str, Any]) -> dict[str, float]:
    """Each team merged into another (and not split off again) -> when [sim s]."""
    return {m["joined_team_id"]: m["sim_time_s"] for m in report.get("merges", [])
            if m.get("joined_team_id") and not m.get("undone")}


def _joined_title(team_id: str, report: dict[str, Any]) -> str:
    """The teams that merged into ``team_id`` (directly or through another), in order."""
    into = {tid: t.get("merged_into") for tid, t in report["teams"].items()}

    def ends_in(tid: str | None) -> bool:
        seen: set[str] = set()
        while tid is not None and tid not in seen:
            if tid == team_id:
                return True
            seen.add(tid)
            tid = into.get(tid)
        return False

    rows = sorted((at, tid) for tid, at in merge_times(report).items()
                  if tid != team_id and ends_in(into.get(tid)))
    return ", ".join(f"{tid} joined at {at:.1f} s" for at, tid in rows)


def _maps(report: dict[str, Any], out: Path, plt: Any, gaps: Gaps) -> list[str]:
    """The map of each team that exists at the end; a team merged into another has no map
    of its own any more (its last one, in a frame that is gone, is left undrawn)."""
    from schemas.occupancy import FREE_BELOW, OCCUPIED_ABOVE, UNKNOWN
    from sim.errors import WorldError
    from sim.grid import read_nav2

    written = []
    for team_id, team in report["teams"].items():
        if team.get("merged_into"):
            continue
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
        meetings = [m for m in report.get("merges", []) if m.get("team_id") == team_id]
        for rid in team["robot_ids"]:
            path = out / "server" / "trajectories" / f"{rid}_final.csv"
            if not path.exists():
                continue
            stamps, poses = read_trajectory(path, gaps)
            if not len(poses):
                continue
            (line,) = ax.plot(poses[:, 0], poses[:, 1], lw=1, label=rid)
            c = line.get_color()
            ax.plot(*poses[0, :2], "o", color=c, ms=7, mfc="white", mew=2)
            ax.plot(*poses[-1, :2], "s", color=c, ms=6)
            for m in meetings:
                if rid in m.get("robots", []):
                    k = int(np.searchsorted(stamps, m["sim_time_s"] * 1e9).clip(0, len(stamps) - 1))
                    ax.plot(*poses[k, :2], "*", color=c, ms=13, mec="k", mew=0.6)
        ax.legend(handles=[*ax.get_legend_handles_labels()[0], *_map_key(plt)], fontsize=8,
                  loc="best")
        joined = _joined_title(team_id, report)
        ax.set_title(f"{team_id}: map and trajectories (map frame)"
                     + (f"\n{joined}" if joined else ""), fontsize=10)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        fig.tight_layout()
        name = f"map_{team_id}.png"
        fig.savefig(out / name, dpi=120)
        plt.close(fig)
        written.append(name)
    return written
