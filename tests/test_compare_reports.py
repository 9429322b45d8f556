"""``bench/compare_reports.py``: counters that run on after the finish do not make two runs
that did the same thing differ, unless both ended at the same simulated time."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bench import compare_reports


def _compare(tmp_path: Path, a: dict[str, object], b: dict[str, object],
             capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    pa, pb = tmp_path / "a.json", tmp_path / "b.json"
    pa.write_text(json.dumps(a))
    pb.write_text(json.dumps(b))
    assert compare_reports.main([str(pa), str(pb)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert isinstance(out, dict)
    return out


def test_tag_counters_after_the_finish_are_apart(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    base = {"time_to_threshold_s": 74.0, "tag_counters": {"sightings": 109, "used": 109}}
    later = {**base, "tag_counters": {"sightings": 118, "used": 118}}
    out = _compare(tmp_path, {**base, "sim_time_s": 75.1}, {**later, "sim_time_s": 75.6},
                   capsys)
    assert out["identical"] is True
    assert [d["field"] for d in out["counted_after_the_finish"]] == [
        ".tag_counters.sightings", ".tag_counters.used"]
    # the same end: a real difference
    out = _compare(tmp_path, {**base, "sim_time_s": 75.1}, {**later, "sim_time_s": 75.1},
                   capsys)
    assert out["identical"] is False
    assert len(out["differences"]) == 2
    # anything else always counts
    out = _compare(tmp_path, {**base, "sim_time_s": 75.1},
                   {**base, "time_to_threshold_s": 75.0, "sim_time_s": 75.6}, capsys)
    assert out["identical"] is False
