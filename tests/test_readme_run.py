"""The README's figure, caption and sample output tell of one run of the current code: they are
made from docs/img/demo-run.json, and a fresh run of the default demo (lockstep, so the same
code gives the same run) still gives that file's figures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bench.support import readme_run
from mrslam.demo import DemoConfig

REGENERATE = "python bench/readme.py --write"


def reference() -> dict[str, Any]:
    return json.loads(readme_run.REFERENCE.read_text())


def test_the_readme_says_what_the_reference_run_says() -> None:
    ref = reference()
    readme = readme_run.README.read_text()
    for part, text in readme_run.sections(ref).items():
        assert readme_run.marked(readme, part) == text, f"README's {part}: run {REGENERATE}"
    # the figure was drawn in the same run
    assert readme_run.sha256(readme_run.MAP_PNG) == ref["map_sha256"], REGENERATE
    fig = ref["figures"]
    assert f"reached {fig['threshold']:.0%} in {fig['sim_time_to_threshold_s']:.0f} s sim" \
        in ref["output"]
    # ... and it is the run `make demo` makes
    defaults = DemoConfig()
    assert (fig["scenario"], fig["seed"], fig["lockstep"]) == (
        defaults.scenario, defaults.seed, defaults.lockstep)


def test_the_caption_tells_who_joined_whom_when_and_how() -> None:
    report = {"scenario": "s", "seed": 0, "lockstep": True, "threshold": 0.98,
              "robots_spawn": {"r1": [], "r2": [], "r3": []}, "reached": True,
              "sim_time_to_threshold_s": 77.96, "end": "finished",
              "teams": {"team-r1": {"robot_ids": ["r1", "r2", "r3"]},
                        "team-r2": {"robot_ids": ["r2"], "merged_into": "team-r1"},
                        "team-r3": {"robot_ids": ["r3"], "merged_into": "team-r1"}},
              "merges": [{"sim_time_s": 16.2, "team_id": "team-r1", "joined_team_id": "team-r2",
                          "robots": ["r1", "r2"], "kind": "tags", "undone": False},
                         {"sim_time_s": 50.0, "team_id": "team-r1", "joined_team_id": "team-r3",
                          "robots": ["r1", "r2", "r3"], "kind": "map", "undone": False}]}
    text = " ".join(readme_run.caption(readme_run.figures(report)).split())
    assert "three robots" in text and "end as one team with one map" in text
    assert ("(r2 joined r1 at 16.2 s on tag sightings, r3 joined them at 50.0 s on the maps "
            "alone; 98 % covered after 78 s of simulated time)") in text


@pytest.mark.e2e
def test_a_fresh_default_run_gives_the_readmes_figures(tmp_path: Path) -> None:
    """The default demo as `make demo` runs it (without the recording, which changes nothing
    the robots do): who joined whom, when and how, and when it reached the threshold."""
    from mrslam.demo import run

    report = run({"out": str(tmp_path / "run"), "record": False}, progress=False)
    assert readme_run.figures(report) == reference()["figures"], (
        f"the default demo no longer does what the README says: if that is meant, {REGENERATE}")
