"""``bench/load.py --quick``: a real server and generated robots on loopback; the JSON it prints
has the promised shape, and at N=2 the server answered the scans with finite latencies."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: starts the server and generator processes: the e2e tier
#: real time against wall clocks: run alone, after the others (``make test``)
pytestmark = [pytest.mark.e2e, pytest.mark.realtime]

RUN_KEYS = {"robots", "scan_to_command_p50_ms", "scan_to_command_p99_ms",
            "dropped_scan_fraction", "server_cpu_cores", "server_rss_mb"}


def test_quick_load_run(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "load.py"), "--quick",
                           "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    assert {"runs", "capacity_robots", "cores", "settings"} <= set(out)
    assert out["cores"] >= 1
    runs = out["runs"]
    assert [r["robots"] for r in runs][:1] == [2]
    for r in runs:
        assert set(r) >= RUN_KEYS, r
        assert 0.0 <= r["dropped_scan_fraction"] <= 1.0
        assert r["server_rss_mb"] > 0
    cap = out["capacity_robots"]
    assert cap is None or cap in [r["robots"] for r in runs if r["ok"]]
    two = runs[0]
    assert two["valid"], two["generator"]              # the generator kept 10 Hz
    assert two["scans_answered"] > 0.9 * two["scans_sent"] > 0, two
    p50, p99 = two["scan_to_command_p50_ms"], two["scan_to_command_p99_ms"]
    assert p50 is not None and p99 is not None and math.isfinite(p99)
    assert 0 < p50 <= p99 < 1000
    assert two["server_cpu_cores"] > 0
    assert two["server_errors"] == 0 and two["server_exit_code"] == 0
