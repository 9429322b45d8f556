"""Logs whose stamps jump: the outlier goes, not the run (``server.offline.logs.stamps``,
slam-log)."""

from __future__ import annotations

import bz2
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from mrslam.cli import app
from server.offline.evaluation import evaluate
from server.offline.logs.stamps import EARLY_NUDGE_S, plan_stamps
from tests.conftest import DATA

CARMEN = DATA / "carmen"
needs_data = pytest.mark.skipif(not CARMEN.is_dir(), reason="no ../shared/data/carmen")


def ticks(n: int, t0: float = 100.0, dt: float = 0.1) -> list[float]:
    return [t0 + dt * k for k in range(n)]


def test_a_stamp_ahead_of_its_neighbours_is_dropped_alone() -> None:
    s = ticks(50)
    s[20] += 3600.0
    s[35] += 0.5          # a small spike: five periods ahead
    plan = plan_stamps(s)
    assert plan.dropped_ahead == [20, 35] and not plan.dropped_behind and not plan.steps
    assert plan.keep == [k for k in range(50) if k not in (20, 35)]


def test_a_stamp_behind_alone_is_dropped_and_a_step_back_is_rebased() -> None:
    s = ticks(60)
    s[10] -= 3600.0                          # a glitch
    s[30:] = [t - 3600.0 for t in s[30:]]    # the clock stepped back and stays there
    plan = plan_stamps(s)
    assert plan.dropped_behind == [10] and not plan.dropped_ahead
    assert [i for i, _ in plan.steps] == [30]
    assert len(plan.keep) == 59
    assert np.all(np.diff(plan.stamps_s) > 0)
    np.testing.assert_allclose(np.diff(plan.stamps_s)[28:], 0.1, atol=1e-6)


def test_gaps_forward_are_kept() -> None:
    s = ticks(20) + ticks(20, t0=500.0)      # the logger paused for six minutes
    plan = plan_stamps(s)
    assert plan.keep == list(range(40)) and plan.stamps_s == s


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-1e4, 1e4, allow_nan=False), min_size=1, max_size=80),
       st.data())
def test_planned_stamps_never_go_back_and_clean_logs_lose_nothing(jumps: list[float],
                                                                  data: st.DataObject) -> None:
    clean = ticks(len(jumps))
    assert plan_stamps(clean).keep == list(range(len(clean)))
    noisy = [t + (j if data.draw(st.booleans()) else 0.0) for t, j in zip(clean, jumps,
                                                                         strict=True)]
    plan = plan_stamps(noisy)
    assert np.all(np.diff(plan.stamps_s) >= 0)
    assert sorted(plan.keep + plan.dropped_ahead + plan.dropped_behind) == list(range(len(noisy)))


def fr079_head(n_scans: int) -> list[str]:
    """The lines of FR079 up to its ``n_scans``-th FLASER line."""
    lines: list[str] = []
    with bz2.open(CARMEN / "fr079.clf.bz2", "rt") as f:
        n = 0
        for line in f:
            lines.append(line)
            n += line.startswith("FLASER")
            if n == n_scans:
                break
    return lines


@needs_data
def test_slam_log_on_a_real_log_with_a_jumping_stamp_keeps_the_rest(tmp_path: Path) -> None:
    """FR079's first 400 scans, once as recorded and once with one scan stamped an hour
    ahead and a later one a minute behind: every other scan gets its pose, and the same."""
    lines = fr079_head(400)
    flaser = [i for i, line in enumerate(lines) if line.startswith("FLASER")]

    def restamp(line: str, dt: float) -> str:
        w = line.split()
        w[-3] = f"{float(w[-3]) + dt:.6f}"
        return " ".join(w) + "\n"

    bad = list(lines)
    bad[flaser[120]] = restamp(bad[flaser[120]], 3600.0)
    bad[flaser[260]] = restamp(bad[flaser[260]], -60.0)
    outs = {}
    for name, text in (("clean", lines), ("bad", bad)):
        (tmp_path / f"{name}.clf").write_text("".join(text))
        outs[name] = tmp_path / name
        res = CliRunner().invoke(app, ["slam-log", str(tmp_path / f"{name}.clf"),
                                       "--out", str(outs[name])])
        assert res.exit_code == 0, res.output
    summary = json.loads((outs["bad"] / "summary.json").read_text())
    assert summary["scans"] == 398 >= 0.99 * 400
    assert summary["stamps_dropped_ahead"] == 1 and summary["stamps_dropped_behind"] == 1
    clean = {ln.split()[0]: np.array(ln.split()[1:], float)
             for ln in (outs["clean"] / "poses.txt").read_text().splitlines()}
    got = {ln.split()[0]: np.array(ln.split()[1:], float)
           for ln in (outs["bad"] / "poses.txt").read_text().splitlines()}
    assert set(got) < set(clean)
    err = max(float(np.hypot(*(got[k][:2] - clean[k][:2]))) for k in got)
    assert err < 0.05
    a = evaluate(outs["clean"] / "poses.txt", CARMEN / "fr079.relations")
    b = evaluate(outs["bad"] / "poses.txt", CARMEN / "fr079.relations")
    assert b.matched >= a.matched - 2 and b.trans_mean_m < a.trans_mean_m + 0.01


def test_a_scan_a_few_ms_early_is_kept_in_file_order_and_fed_just_after() -> None:
    """The Intel Research Lab pattern: a line stamped 6 ms before the line above it."""
    s = ticks(40, dt=0.2)
    for k in (5, 17, 18, 30):
        s[k] = s[k - 1] - 0.006
    plan = plan_stamps(s)
    assert plan.keep == list(range(40)) and plan.early == [5, 17, 18, 30]
    assert not plan.dropped_ahead and not plan.dropped_behind and not plan.steps
    assert np.all(np.diff(plan.stamps_s) > 0)
    assert plan.stamps_s[5] == pytest.approx(s[4] + EARLY_NUDGE_S)
    others = [k for k in range(40) if k not in plan.early]
    assert [plan.stamps_s[k] for k in others] == [s[k] for k in others]


def test_further_behind_than_jitter_is_still_an_outlier() -> None:
    s = ticks(40, dt=0.2)
    s[12] = s[11] - 0.15          # three quarters of a period behind: not jitter
    s[25] = s[24] - 0.09          # less than half a period: jitter
    plan = plan_stamps(s)
    assert plan.dropped_behind == [12] and plan.early == [25]
    assert plan_stamps(s, jitter_fraction=0.8).early == [12, 25]


def jittered_fr079(tmp_path: Path, n_scans: int, every: int) -> tuple[Path, Path, list[str]]:
    """FR079's first scans as recorded, and with every ``every``-th FLASER line stamped 6 ms
    before the FLASER line above it (as 6.4 % of the Intel log's are). Returns both logs and
    the jittered log's FLASER stamps as written."""
    lines = fr079_head(n_scans)
    flaser = [i for i, line in enumerate(lines) if line.startswith("FLASER")]
    bad = list(lines)
    for k in range(every, len(flaser), every):
        words = bad[flaser[k]].split()
        words[-3] = f"{float(lines[flaser[k - 1]].split()[-3]) - 0.006:.6f}"
        bad[flaser[k]] = " ".join(words) + "\n"
    clean, jittered = tmp_path / "clean.clf", tmp_path / "jittered.clf"
    clean.write_text("".join(lines))
    jittered.write_text("".join(bad))
    return clean, jittered, [bad[i].split()[-3] for i in flaser]


@needs_data
def test_slam_log_poses_every_jittered_scan_with_its_own_stamp(tmp_path: Path) -> None:
    clean, jittered, written = jittered_fr079(tmp_path, 400, 15)
    outs = {}
    for log_file in (clean, jittered):
        outs[log_file.stem] = tmp_path / f"out-{log_file.stem}"
        res = CliRunner().invoke(app, ["slam-log", str(log_file), "--out",
                                       str(outs[log_file.stem])])
        assert res.exit_code == 0, res.output
    summary = json.loads((outs["jittered"] / "summary.json").read_text())
    assert summary["scans"] == summary["scans_in_log"] == 400
    assert summary["stamps_early_kept"] == 26 and summary["stamps_dropped_behind"] == 0
    rows = (outs["jittered"] / "poses.txt").read_text().splitlines()
    assert [r.split()[0] for r in rows] == written       # file order, the stamps as written
    a = np.loadtxt(outs["clean"] / "poses.txt")[:, 1:]
    b = np.loadtxt(outs["jittered"] / "poses.txt")[:, 1:]
    assert np.hypot(*(a[:, :2] - b[:, :2]).T).max() < 0.05
