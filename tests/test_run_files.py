"""A run folder's readers and the report tolerate missing and damaged files: what is intact is
read, what is not is named, nothing raises."""

from __future__ import annotations

import io
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from mrslam.report import beside_dissertation, build_report, print_summary
from mrslam.run_files import Gaps, read_json, read_trajectory, read_truth
from server.runtime.outputs import write_trajectory


def test_a_trajectory_reads_back_what_the_server_wrote(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    stamps = np.cumsum(rng.integers(1, 10**9, 50)).astype(np.int64)
    poses = rng.uniform(-50, 50, (50, 3))
    poses[:, 2] = rng.uniform(-np.pi, np.pi, 50)
    path = tmp_path / "r1_online.csv"
    write_trajectory(path, stamps, poses)
    gaps = Gaps(tmp_path)
    got_stamps, got_poses = read_trajectory(path, gaps)
    assert np.array_equal(got_stamps, stamps)
    assert np.allclose(got_poses, poses, atol=1e-5) and gaps.notes == []


def test_damaged_trajectory_rows_are_skipped_and_named(tmp_path: Path) -> None:
    path = tmp_path / "r1_final.csv"
    path.write_text("stamp_ns,x_m,y_m,theta_rad\n1000,1.0,2.0,0.1\nxx,1,2,3\n2000,1.5,nan,0\n"
                    "3000,2.0,2.5,0.2\n4000,2.5,3.0,0.3,9\n5000,3.0,3")   # cut short at the end
    gaps = Gaps(tmp_path)
    stamps, poses = read_trajectory(path, gaps)
    assert stamps.tolist() == [1000, 3000] and poses.shape == (2, 3)
    assert gaps.notes == ["r1_final.csv: 4 damaged row(s) skipped"]


def test_a_missing_trajectory_is_empty_and_named(tmp_path: Path) -> None:
    gaps = Gaps(tmp_path)
    stamps, poses = read_trajectory(tmp_path / "trajectories" / "r9_online.csv", gaps)
    assert stamps.shape == (0,) and poses.shape == (0, 3)
    assert gaps.notes == ["trajectories/r9_online.csv: missing"]


@pytest.mark.parametrize(("text", "problem"), [
    (None, "missing"), ('{"teams": {"team-r1": {"robot_ids"', "not valid JSON"),
    ("[1, 2]", "expected a JSON object, found list")])
def test_a_summary_that_is_missing_or_cut_short_reads_as_empty(
        tmp_path: Path, text: str | None, problem: str) -> None:
    path = tmp_path / "summary.json"
    if text is not None:
        path.write_text(text)
    gaps = Gaps(tmp_path)
    assert read_json(path, gaps) == {}
    assert len(gaps.notes) == 1 and gaps.notes[0].startswith(f"summary.json: {problem}")


def truth_line(stamp_s: float, x: float) -> str:
    return json.dumps({"stamp_ns": int(stamp_s * 1e9), "poses": [
        {"robot_id": "r1", "pose": [x, 0.0, 0.0], "collisions": 0, "distance_m": x},
        {"robot_id": "r2", "pose": [0.0, x, 0.0], "collisions": 1, "distance_m": 2 * x}]})


def test_truth_cut_short_at_the_end_is_normal_damage_inside_is_named(tmp_path: Path) -> None:
    path = tmp_path / "truth.jsonl"
    lines = [truth_line(0.1 * k, 0.01 * k) for k in range(10)]
    path.write_text("\n".join(lines) + "\n" + lines[0][:30])
    gaps = Gaps(tmp_path)
    truth = read_truth(path, gaps)
    assert len(truth["r1"]["stamps_ns"]) == 10 and gaps.notes == []
    assert truth["r2"]["collisions"] == 1 and truth["r2"]["distance_m"] == pytest.approx(0.18)
    path.write_text("\n".join([*lines[:4], "{broken", '{"poses": [{}]}', *lines[4:]]) + "\n")
    truth = read_truth(path, gaps)
    assert len(truth["r1"]["stamps_ns"]) == 10
    assert gaps.notes == ["truth.jsonl: 2 damaged line(s) skipped"]


def run_folder(tmp_path: Path) -> Path:
    """A run whose simulator wrote its truth and whose server left nothing."""
    (tmp_path / "sim").mkdir()
    (tmp_path / "sim" / "truth.jsonl").write_text(
        "\n".join(truth_line(0.1 * k, 0.01 * k) for k in range(10)) + "\n")
    return tmp_path


def report_of(run: Path) -> dict[str, Any]:
    cfg = SimpleNamespace(seed=0, explorer="voronoi", lockstep=True)
    plan = {"title": "test", "world": str(run / "no.world"), "threshold": 0.95,
            "robots": {"r1": [0, 0, 0], "r2": [0, 0, 0]}, "area_m2": 10.0,
            "nominal_area_m2": None, "truth_grid": None, "reported": {}}
    watch = {"end": "server-died", "sim_time_s": 0.9, "bytes_sent": {"r1": 123},
             "events": [{"kind": "merge", "stamp_ns": 5, "robot_ids": ["r1", "r2"],
                         "message": "seen on the bus"}],
             "server_restarts": [{"pid": 7, "signal": "SIGKILL", "exit_code": -9,
                                  "restarted": False, "wall_time_s": 3.0, "sim_time_s": 0.5}]}
    return build_report(cfg, plan, run, watch, wall_time_s=4.0)


def test_without_the_servers_outputs_the_report_holds_the_truth_and_names_the_gap(
        tmp_path: Path) -> None:
    report = report_of(run_folder(tmp_path))
    assert report["missing"] == ["server/summary.json: missing"]
    assert not report["reached"] and report["teams"] == {} and report["merges"] == []
    assert report["robots"]["r1"]["distance_m"] == pytest.approx(0.09)
    assert report["robots"]["r1"]["bytes_sent"] == 123
    assert report["robots"]["r2"]["collisions"] == 1
    assert report["robots"]["r1"]["max_position_error_m"] is None
    assert report["events"][0]["message"] == "seen on the bus"   # the monitor's, instead
    assert report["server_restarts"][0]["signal"] == "SIGKILL"
    json.dumps(report)   # it is written as it is
    buf = io.StringIO()
    print_summary(report, Console(file=buf, width=300))
    text = buf.getvalue()
    assert "did NOT reach 95%" in text and "no team known" in text
    assert "server died (SIGKILL)" in text and "not restarted" in text
    assert "server/summary.json: missing" in text


def test_the_dissertations_figures_only_beside_one_of_its_own_cases(tmp_path: Path) -> None:
    """A packaged scenario has no published figures (the key was always ``{}``); a case of
    the dissertation's scenarios file has them, next to ours of the same kind."""
    assert "dissertation" not in report_of(run_folder(tmp_path))
    robots = {"r1": {"max_position_error_m": 0.05, "max_yaw_error_rad": 0.01},
              "r2": {"max_position_error_m": 0.12, "max_yaw_error_rad": None},
              "r3": {"max_position_error_m": None, "max_yaw_error_rad": None}}
    reported = {"iterations_to_finish": 153, "max_abs_position_error_m": 0.2}
    assert beside_dissertation("thesis-case-2", reported, robots) == {
        "case": "thesis-case-2", "reported": reported,
        "measured": {"max_position_error_m": 0.12, "max_yaw_error_rad": 0.01}}


def test_a_refresh_left_by_a_dead_server_is_scored_and_its_damage_named(tmp_path: Path) -> None:
    run = run_folder(tmp_path)
    srv = run / "server"
    (srv / "trajectories").mkdir(parents=True)
    stamps = (np.arange(10) * 1e8).astype(np.int64)
    poses = np.column_stack([np.arange(10) * 0.01, np.zeros(10), np.zeros(10)])
    write_trajectory(srv / "trajectories" / "r1_online.csv", stamps, poses)
    (srv / "trajectories" / "r1_final.csv").write_text("stamp_ns,x_m,y_m,theta_rad\n0,0.0,")
    history = [[int(k * 1e8), 0.1 * k] for k in range(10)]
    (srv / "summary.json").write_text(json.dumps({
        "running": True, "robots": {"r1": {"scans": 10, "mode": "exploring"}},
        "teams": {"team-r1": {"robot_ids": ["r1"], "coverage": 0.9,
                              "coverage_history": history}}}))
    report = report_of(run)
    assert report["teams"]["team-r1"]["coverage"] == 0.9
    assert report["teams"]["team-r1"]["sim_time_to_threshold_s"] is None
    r1 = report["robots"]["r1"]
    assert r1["team_id"] == "team-r1" and r1["scans"] == 10
    assert r1["max_position_error_m"] == pytest.approx(0.0, abs=1e-6)
    assert r1["ate_rmse_m"] is None   # the final trajectory held nothing intact
    assert report["robots"]["r2"]["team_id"] is None   # in the truth, not in the server's files
    assert set(report["missing"]) == {
        "server/summary.json: written while the server ran (its last periodic refresh): the "
        "server did not stop cleanly",
        "server/trajectories/r1_final.csv: 1 damaged row(s) skipped",
        "server/maps/team-r1/map.yaml: missing"}
