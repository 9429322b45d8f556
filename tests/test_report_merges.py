"""The report's merge errors: the transform between two robots' start frames, as the merge
committed it and as the final joint map has it, against the simulator's truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mrslam.report import _in_team_error, first_sight, merge_errors
from mrslam.run_files import Gaps
from schemas.se2 import compose

A0 = np.array([-23.0, -22.0, 0.0])      # where robots a and b started (world)
B0 = np.array([-5.0, 20.0, 0.3])


def _merge(T_joint: np.ndarray) -> dict[str, object]:
    return {"stamp_ns": 10**9, "team_id": "t-a", "joined_team_id": "t-b",
            "robots_a": ["a"], "robots_b": ["b"], "sightings": [], "T_joint": T_joint,
            "T_fused": T_joint, "T_direct_first": T_joint}


def test_final_start_frame_error_is_read_from_the_final_joint_map() -> None:
    own = {"a": A0, "b": B0}
    # truth of b's frame in a's: a's frame has yaw 0, so a translation and b's yaw
    T_true = np.array([B0[0] - A0[0], B0[1] - A0[1], B0[2]])
    off = np.array([0.3, -0.1, math.radians(2.0)])            # committed 2° and 0.3 m off
    stamps = np.array([0, 10**8])
    first_online = {"a": np.zeros(3), "b": np.array([0.01, 0.0, 0.0])}
    # in the final map, b's first pose (its online origin moved 1 cm) is 2 cm off the truth
    b_final0 = compose(T_true + np.array([0.02, 0.0, 0.0]), first_online["b"])
    final = {"a": (stamps, np.array([np.zeros(3), np.zeros(3)])),
             "b": (stamps, np.array([b_final0, b_final0]))}
    rows = merge_errors([_merge(T_true + off)], own, final, None, first_online,
                        {"a": "t-a", "b": "t-a"})
    r = rows[0]
    assert r["joint_error_m"] > 0.25 and r["joint_error_deg"] > 1.9
    assert abs(r["final_error_m"] - 0.02) < 1e-3 and r["final_error_deg"] < 1e-6
    # robots that did not end in one team have no final error
    rows = merge_errors([_merge(T_true)], own, final, None, first_online,
                        {"a": "t-a", "b": "t-b"})
    assert "final_error_m" not in rows[0] and rows[0]["joint_error_m"] < 1e-9


def _summary(report: dict) -> str:
    import io

    from rich.console import Console

    from mrslam.report import print_summary

    buf = io.StringIO()
    print_summary(report, Console(file=buf, width=200))
    return buf.getvalue()


def test_summary_names_the_team_that_fell_short() -> None:
    """A robot that never met the others (here shut in a room) keeps the run from its threshold;
    the summary says which team and how far it got, not a time of nan."""
    robot = {"distance_m": 0.0, "max_position_error_m": 0.004, "max_yaw_error_rad": 0.002,
             "ate_rmse_m": 0.001, "collisions": 0, "bytes_sent": 10}
    teams = {"team-r1": {"robot_ids": ["r1", "r2"], "coverage": 0.97, "reached": True},
             "team-r2": {"robot_ids": ["r2"], "coverage": 0.6, "reached": False,
                         "merged_into": "team-r1"},
             "team-r3": {"robot_ids": ["r3"], "coverage": 0.04, "reached": False}}
    report = {"scenario": "w", "reached": False, "threshold": 0.95, "teams": teams,
              "sim_time_to_threshold_s": None, "sim_time_s": 86.0, "wall_time_s": 25.0,
              "robots": {"r1": robot, "r2": robot, "r3": robot}, "true_coverage": 0.04,
              "phantom_area_m2": 0.0, "end": "finished"}
    text = _summary(report)
    assert "did NOT reach 95% in 86 s sim: team-r3 (r3) 4%" in text
    assert "team-r2" not in text and "nan" not in text
    report.update(reached=True, sim_time_to_threshold_s=70.0, teams={"team-r1": teams["team-r1"]})
    assert "reached 95% in 70 s sim" in _summary(report)


def test_the_first_team_to_the_threshold_counts_though_a_lone_robot_joined_it_later() -> None:
    """Four robots' team reached 90 % at 370 s; the fifth, alone all along, joined it at 859 s:
    the run reached its threshold at 860 s, the first team at 370 s."""
    from mrslam.report import threshold_times

    teams = {"team-r1": {"reached": True, "sim_time_to_threshold_s": 860.0},
             "team-r2": {"reached": True, "sim_time_to_threshold_s": 370.0,
                         "merged_into": "team-r1"},
             "team-r4": {"reached": False, "sim_time_to_threshold_s": None,
                         "merged_into": "team-r2"}}
    assert threshold_times(teams) == (True, 860.0, 370.0)
    teams["team-r1"] = {"reached": False, "sim_time_to_threshold_s": None}
    assert threshold_times(teams) == (False, None, 370.0)
    assert threshold_times({}) == (False, None, None)


def test_first_sight_is_when_the_teams_could_first_see_each_other() -> None:
    """r1 stands still; r2 drives along y = 4 from x = 0 to 20 at 1 m/s. A wall on x = 8 from
    y = -5 to 5 hides r2 from r1 (at (10, 0)) while r2 is left of it: with the wall, the
    first sight is when r2 reaches x = 8; without it, as soon as r2 is within
    10 m. A merge of robots that never came within 10 m, or one before any sight, gets None."""
    stamps = np.arange(0, 21) * 1_000_000_000
    truth = {"r1": {"stamps_ns": stamps, "poses": np.tile([10.0, 0.0, 0.0], (21, 1))},
             "r2": {"stamps_ns": stamps,
                    "poses": np.column_stack([np.arange(21.0), np.full(21, 4.0), np.zeros(21)])},
             "r3": {"stamps_ns": stamps, "poses": np.tile([50.0, 50.0, 0.0], (21, 1))}}
    wall = np.array([[8.0, -5.0, 8.0, 5.0]])
    merges = [{"stamp_ns": 20_000_000_000, "robots_a": ["r1"], "robots_b": ["r2"]},
              {"stamp_ns": 20_000_000_000, "robots_a": ["r1", "r2"], "robots_b": ["r3"]},
              {"stamp_ns": 3_000_000_000, "robots_a": ["r1"], "robots_b": ["r2"]}]
    # in the open: within 10 m of (10, 0) along y = 4 once x ≥ 10 − √84 ≈ 0.83, so at t = 1 s.
    # With the wall: for x < 8 the line to r2 crosses x = 8 at y = 8 / (10 − x) < 5, blocked;
    # from x = 8 on it clears, so at t = 8 s. The third merge (at 3 s) comes before that.
    assert first_sight(merges, truth, np.zeros((0, 4))) == [1.0, None, 1.0]
    assert first_sight(merges, truth, wall) == [8.0, None, None]


def test_a_false_merge_has_a_named_key_and_old_reports_still_read() -> None:
    from mrslam.report import is_false_merge

    own = {"a": A0, "b": B0}
    T_true = np.array([B0[0] - A0[0], B0[1] - A0[1], B0[2]])
    (row,) = merge_errors([_merge(T_true + np.array([1.0, 0.0, 0.0]))], own)
    assert row["false_merge"] is True and "false" not in row and is_false_merge(row)
    (row,) = merge_errors([_merge(T_true)], own)
    assert row["false_merge"] is False and not is_false_merge(row)
    assert is_false_merge({"false": True}) and not is_false_merge({})


def test_figures_cap_coverage_label_merges_and_key_the_maps(tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mrslam.figures import write_figures
    from mrslam.run_files import Gaps
    from server.runtime.outputs import write_trajectory
    from sim.grid import OccupancyGrid, write_nav2

    cells = np.zeros((40, 60), np.int8)
    cells[0, :] = 100
    write_nav2(OccupancyGrid(cells, 0.1, (0.0, 0.0, 0.0)), tmp_path / "server/maps/t1")
    stamps = np.arange(0, 30, dtype=np.int64) * 10**8
    for rid, y in (("a", 1.0), ("b", 3.0)):
        poses = np.column_stack([np.linspace(0.5, 5.0, 30), np.full(30, y), np.zeros(30)])
        (tmp_path / "server/trajectories").mkdir(parents=True, exist_ok=True)
        write_trajectory(tmp_path / f"server/trajectories/{rid}_final.csv", stamps, poses)
    report = {"scenario": "s", "threshold": 0.9,
              "teams": {"t1": {"robot_ids": ["a", "b"],
                               "coverage_history": [[0.0, 0.2], [1.0, 0.95], [2.0, 1.3]]}},
              "events": [{"kind": "merge", "stamp_ns": 10**9}, {"kind": "merge", "stamp_ns": 2e9}],
              "merges": [{"team_id": "t1", "robots": ["a", "b"], "sim_time_s": 1.5}],
              "robots": {}}
    shown: dict[str, object] = {}
    real_savefig = plt.Figure.savefig

    def keep(fig: object, fname: object, *args: object, **kw: object) -> None:
        shown[Path(str(fname)).name] = fig
        real_savefig(fig, fname, *args, **kw)  # type: ignore[arg-type]

    plt.Figure.savefig = keep  # type: ignore[method-assign]
    try:
        written = write_figures(report, tmp_path, Gaps(tmp_path))
    finally:
        plt.Figure.savefig = real_savefig  # type: ignore[method-assign]
    assert written == ["coverage.png", "pose_error.png", "map_t1.png"]
    cov = shown["coverage.png"].axes[0]  # type: ignore[attr-defined]
    assert max(max(line.get_ydata()) for line in cov.lines[:1]) == 100.0
    assert cov.get_ylim()[1] <= 105 and "capped" in cov.get_ylabel()
    labels = [t.get_text() for t in cov.get_legend().get_texts()]
    assert labels.count("merge") == 1 and "threshold" in labels
    m = shown["map_t1.png"].axes[0]  # type: ignore[attr-defined]
    keys = [t.get_text() for t in m.get_legend().get_texts()]
    for k in ("a", "b", "start", "end", "merge (meeting)", "free", "occupied", "unknown"):
        assert k in keys
    stars = [ln for ln in m.lines if ln.get_marker() == "*"]
    assert len(stars) == 2 and stars[0].get_xydata()[0][0] > 2.5   # at 1.5 s of 3 s


def test_only_the_teams_at_the_end_have_maps_and_theirs_name_who_joined(tmp_path: Path) -> None:
    """t2 merged into t1 at 1.5 s; the server's last map of t2 (in t2's frame, gone since) is
    still in the run folder: it is not drawn, and t1's map says t2 joined it then."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mrslam.figures import write_figures
    from mrslam.run_files import Gaps
    from sim.grid import OccupancyGrid, write_nav2

    cells = np.zeros((40, 60), np.int8)
    for team in ("t1", "t2"):
        write_nav2(OccupancyGrid(cells, 0.1, (0.0, 0.0, 0.0)), tmp_path / f"server/maps/{team}")
    history = [[0.0, 0.2], [2.0, 0.5]]
    report = {"scenario": "s", "threshold": 0.9, "robots": {}, "events": [],
              "teams": {"t1": {"robot_ids": ["a", "b"], "coverage_history": history},
                        "t2": {"robot_ids": ["b"], "merged_into": "t1",
                               "coverage_history": history[:1]}},
              "merges": [{"team_id": "t1", "joined_team_id": "t2", "robots": ["a", "b"],
                          "sim_time_s": 1.5, "undone": False}]}
    titles: dict[str, str] = {}
    legends: dict[str, list[str]] = {}
    real_savefig = plt.Figure.savefig

    def keep(fig: object, fname: object, *args: object, **kw: object) -> None:
        ax = fig.axes[0]  # type: ignore[attr-defined]
        titles[Path(str(fname)).name] = ax.get_title()
        legend = ax.get_legend()
        legends[Path(str(fname)).name] = [t.get_text() for t in legend.get_texts()] \
            if legend else []
        real_savefig(fig, fname, *args, **kw)  # type: ignore[arg-type]

    plt.Figure.savefig = keep  # type: ignore[method-assign]
    try:
        written = write_figures(report, tmp_path, Gaps(tmp_path))
    finally:
        plt.Figure.savefig = real_savefig  # type: ignore[method-assign]
    assert written == ["coverage.png", "pose_error.png", "map_t1.png"]
    assert not (tmp_path / "map_t2.png").exists()
    assert "t2 joined at 1.5 s" in titles["map_t1.png"]
    assert "t2 (b), into t1 at 1.5 s" in legends["coverage.png"]


def test_a_robots_error_in_its_team_map_is_scored_in_the_first_robots_frame(
        tmp_path: Path) -> None:
    """b's poses in a's own frame (``b_online_in_a.csv``), a's frame placed in the world by
    a's start: b was 0.2 m off where the team's map put it, though its own frame may say
    less; robots never in a team, or whose first robot's truth is unknown, get None."""
    from server.runtime.outputs import write_trajectory

    stamps = np.arange(5) * 10**8
    truth_b = np.array([compose(B0, np.array([0.1 * k, 0.0, 0.0])) for k in range(5)])
    in_a = np.array([compose(np.array([-A0[0], -A0[1], 0.0]), p) for p in truth_b])
    in_a[3, 1] += 0.2                            # one pose 0.2 m off in the team's map
    write_trajectory(tmp_path / "b_online_in_a.csv", stamps, in_a)
    truth = {"b": {"stamps_ns": stamps, "poses": truth_b}}
    gaps = Gaps(tmp_path)
    err = _in_team_error("b", tmp_path, {"a": A0, "b": B0}, truth, gaps)
    assert err is not None and abs(err - 0.2) < 1e-6
    assert _in_team_error("a", tmp_path, {"a": A0, "b": B0}, truth, gaps) is None
    assert _in_team_error("b", tmp_path, {"b": B0}, truth, gaps) is None
