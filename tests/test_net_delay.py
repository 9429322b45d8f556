"""A late network is not a stepped clock: a robot behind a relay that stalls, jitters and cuts
its link, against a real server process (``server.runtime.clock``, ``bench.support.relay``).

The relay holds the robot's bytes as a Wi-Fi link does while the robot roams between access
points, then lets them through at once. Its stamps were right all along: the server must not
re-base it, nor refuse its scans, and must answer it again as soon as its scans arrive.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bench.support.fleet import RoomRobot, ServerProcess
from bench.support.relay import Relay

pytestmark = pytest.mark.e2e


@contextlib.contextmanager
def behind_a_relay(folder: Path, seed: int) -> Iterator[tuple[ServerProcess, Relay]]:
    """A server on this machine's clock, and a relay with 30 ms of jitter in front of it;
    the server is stopped (exit code 0) and the summary written when the block ends."""
    srv = ServerProcess(folder, {"explore": {"total_area_m2": 48.0}})
    relay = None
    try:
        srv.client().close()
        relay = Relay(srv.endpoint, jitter_s=0.03, seed=seed)
        yield srv, relay
    finally:
        code = srv.stop()
        if relay is not None:
            relay.close()
    assert code == 0


def registry(folder: Path) -> dict[str, Any]:
    return dict(json.loads((folder / "server" / "summary.json").read_text())["registry"])


def test_delay_bursts_jitter_and_a_cut_link_neither_rebase_nor_refuse(tmp_path: Path) -> None:
    with behind_a_relay(tmp_path, seed=1) as (srv, relay):
        r1 = RoomRobot(srv.endpoint, "r1").start()
        r2 = RoomRobot(relay.endpoint, "r2").start()
        try:
            time.sleep(4.0)
            ends = []
            for burst_s in (0.5, 2.0, 5.0):
                relay.hold(burst_s)
                time.sleep(burst_s)
                ends.append(time.monotonic())
                time.sleep(3.0)
            relay.cut(1.0)
            time.sleep(6.0)
            t_end = time.monotonic()
            for end in ends:   # answered again within a second of each burst's end
                assert r2.longest_silence_s(end + 0.5, end + 3.0) < 1.0
            assert r1.longest_silence_s(ends[0] - 1.0, t_end) < 1.0
            assert r2.answered_since(t_end - 3.0) >= 20    # and after the cut
            assert relay.held_chunks > 0
        finally:
            r1.close()
            r2.close()
    reg = registry(tmp_path)
    r2s = reg["r2"]
    assert not [k for k in r2s if k.startswith("refused")], r2s
    assert "clock_steps" not in r2s and "clock_adjustments" not in r2s, r2s
    assert abs(r2s.get("clock_offset_s", 0.0)) <= 0.02
    assert r2s["accepted_scan"] >= reg["r1"]["accepted_scan"] - 15


def test_a_clock_step_behind_a_jittery_link_is_rebased_within_a_second(tmp_path: Path) -> None:
    with behind_a_relay(tmp_path, seed=2) as (_srv, relay):
        r2 = RoomRobot(relay.endpoint, "r2").start()
        try:
            time.sleep(3.0)
            steps = []
            for step_s in (1.0, -1.0):
                steps.append(time.time())
                r2.clock_offset_ns += round(step_s * 1e9)
                time.sleep(3.0)
                assert r2.longest_silence_s(time.monotonic() - 2.0, time.monotonic()) < 0.5
        finally:
            r2.close()
    r2s = registry(tmp_path)["r2"]
    assert r2s["clock_steps"] == 2, r2s
    for (at_s, step_s), t_step, want in zip(r2s["clock_rebased"], steps, (1.0, -1.0),
                                            strict=True):
        assert step_s == pytest.approx(want, abs=0.05)
        assert 0.0 <= at_s - t_step <= 1.0
    # re-based to the least delay of the three messages that confirmed the step back: the
    # relay's jitter (30 ms) at most, and the machine's own delays (one CI run: 22 ms)
    assert abs(r2s.get("clock_offset_s", 0.0)) <= 0.03 + 0.01
