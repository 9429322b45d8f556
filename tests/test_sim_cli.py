"""``mrslam sim`` as a real process, and its expected failures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest
from typer.testing import CliRunner

from mrslam.cli import app
from schemas import SimGroundTruth
from sim.config import SimConfig, parse_robot_arg, resolve_scene_sensors
from sim.errors import SimError
from tests.conftest import DATA, ROOT

THESIS = DATA / "worlds" / "thesis"


@pytest.mark.e2e
def test_sim_process_runs_a_scenario_standalone_and_writes_truth(tmp_path: Path,
                                                                 endpoint: str) -> None:
    out = tmp_path / "run"
    res = subprocess.run(
        [sys.executable, "-m", "mrslam.cli", "sim", "--scenario", "small-house-3", "--listen",
         endpoint, "--rtf", "50", "--duration", "1.0", "--seed", "3", "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    lines = (out / "truth.jsonl").read_bytes().splitlines()
    assert len(lines) == 10
    first = msgspec.json.decode(lines[0], type=SimGroundTruth)
    assert {p.robot_id: p.pose for p in first.poses} == {
        "r1": (-8.0, 9.0, 0.0), "r2": (-3.0, 9.0, pytest.approx(4.7124 - 2 * 3.141592653589793)),
        "r3": (4.0, -9.0, pytest.approx(3.1416 - 2 * 3.141592653589793))}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 10 and summary["seed"] == 3 and not summary["lockstep"]
    assert (out / "config.yaml").exists()


@pytest.mark.parametrize("args, message", [
    (["--robot", "r1:1,2,x"], "must be numbers"),
    (["--robot", "r/1:1,2"], "does not match"),
    (["--scenario", "no-such-case"], "no scenario 'no-such-case'"),
    (["--world", "/nonexistent.world", "--robot", "r1:0,0"], "no such world file"),
    (["--scenario", "small-house-1", "--robot", "r1:0,9.9,0"], "spawn inside or touching"),
    # the packaged houses were once named after the dissertation's cases, which they are not
    (["--scenario", "thesis-case-4"], "'thesis-case-4' is called 'large-house-5' now"),
])
def test_sim_expected_failures_exit_2_with_one_line(args: list[str], message: str) -> None:
    res = CliRunner().invoke(app, ["sim", *args])
    assert res.exit_code == 2, res.output
    assert message in res.output and len(res.output.strip().splitlines()) == 1


def test_robot_specs_and_scenes() -> None:
    assert parse_robot_arg("r2:1.5,-2") == ("r2", (1.5, -2.0, 0.0), None)
    with pytest.raises(SimError):
        parse_robot_arg("r2")
    # by default the cases that ship with the package, in our own worlds
    world, robots, _ = resolve_scene_sensors(SimConfig(scenario="large-house-5"))
    assert world.name == "large_house.world" and world.is_file() and len(robots) == 5
    world, robots, _ = resolve_scene_sensors(SimConfig(scenario="large-house-5",
                                                       robots={"r9": (0.0, 0.0, 0.0)}))
    assert list(robots) == ["r9"]
    # the dissertation's worlds when its scenarios file is named
    world, robots, _ = resolve_scene_sensors(SimConfig(
        scenario="thesis-case-4", scenarios_file=str(THESIS / "scenarios.yaml")))
    assert world == THESIS / "house_large.world" and len(robots) == 5
