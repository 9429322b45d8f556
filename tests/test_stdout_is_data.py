"""Standard output carries data, standard error the logs: a benchmark's output redirected to a
file parses as JSON, and a daemon run in a pipeline writes nothing on stdout."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import DATA, ROOT

DATED_LOG_LINE = " INFO    "


def parse_json_output(text: str) -> list[object]:
    """A program's stdout as JSON: one document, or one per line (JSON Lines); fails on
    anything else, such as a log line ahead of the JSON."""
    try:
        return [json.loads(text)]
    except json.JSONDecodeError:
        return [json.loads(line) for line in text.splitlines() if line.strip()]


def test_the_parser_refuses_a_log_line_ahead_of_the_json() -> None:
    assert parse_json_output('{"a": 1}\n') == [{"a": 1}]
    assert parse_json_output('{"a": 1}\n{"b": 2}\n') == [{"a": 1}, {"b": 2}]
    with pytest.raises(json.JSONDecodeError):
        parse_json_output('2026-01-01 00:00:00.000 INFO    sim.process: up\n{"a": 1}\n')


@pytest.mark.e2e
@pytest.mark.skipif(not (DATA / "worlds" / "thesis").is_dir(), reason="no ../shared/data")
def test_a_benchmark_that_runs_the_simulator_and_agents_prints_only_json() -> None:
    """bench/sim.py starts ``mrslam sim`` and five agents, which inherit its stdout: their
    log lines went there, ahead of the JSON."""
    res = subprocess.run([sys.executable, "bench/sim.py", "--scans", "20", "--core-steps", "5",
                          "--sim-s", "1"], cwd=ROOT, capture_output=True, text=True,
                         timeout=240)
    assert res.returncode == 0, res.stderr[-2000:]
    (report,) = parse_json_output(res.stdout)
    assert isinstance(report, dict) and report["lockstep"]["sim_time_s"] == pytest.approx(1.0)
    assert DATED_LOG_LINE in res.stderr      # the simulator's log is still there, on stderr


@pytest.mark.e2e
def test_a_daemon_logs_on_stderr_and_leaves_stdout_empty(tmp_path: Path,
                                                         endpoint: str) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "mrslam", "sim", "--world", "sim/worlds/small_house.world",
         "--robot", "r1:-8,9,0", "--listen", endpoint, "--rtf", "50", "--duration", "0.5",
         "--out", str(tmp_path / "run")],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout == ""
    assert DATED_LOG_LINE in res.stderr and "simulated 0.5 s" in res.stderr


@pytest.mark.e2e
def test_compare_reports_prints_json(tmp_path: Path) -> None:
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"scenario": "x", "reached": True, "wall_time_s": 1.0}))
    b.write_text(json.dumps({"scenario": "x", "reached": False, "wall_time_s": 2.0}))
    res = subprocess.run([sys.executable, "bench/compare_reports.py", str(a), str(b)],
                         cwd=ROOT, capture_output=True, text=True, timeout=60, check=True)
    (out,) = parse_json_output(res.stdout)
    assert isinstance(out, dict)
    assert out["differences"] == [{"field": ".reached", "a": True, "b": False}]
