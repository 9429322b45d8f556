"""A full disk degrades the server's state, never its robots: the state folder on a small
tmpfs fills up, the robots keep being answered, the failure is logged once and counted, and
once there is room again journaling resumes from a fresh snapshot, so a server killed after
that resumes with everything (``server.runtime.keeper``)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bench.support.fleet import RoomRobot, ServerProcess
from tests.waiting import within

pytestmark = pytest.mark.e2e


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    folder = tmp_path / "small"
    folder.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(folder)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


def fill(folder: Path) -> Path:
    """Fill the file system of ``folder`` to the last byte."""
    filler = folder / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    try:
        for size in (65536, 1):
            with contextlib.suppress(OSError):
                while os.write(fd, b"\0" * size):
                    pass
    finally:
        os.close(fd)
    return filler


def journal(folder: Path) -> dict[str, Any]:
    try:
        return dict(json.loads((folder / "server" / "summary.json").read_text())["journal"])
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def test_a_full_disk_suspends_the_state_and_writing_resumes_when_there_is_room(
        tmp_path: Path, small_disk: Path) -> None:
    state = small_disk / "state"
    cfg = {"robots": ["r1"], "state_dir": str(state), "outputs_period_s": 0.5,
           "snapshot_period_s": 1.0}
    srv = ServerProcess(tmp_path, cfg)
    robot = None
    try:
        srv.client().close()
        robot = RoomRobot(srv.endpoint, "r1").start()
        time.sleep(3.0)
        filler = fill(small_disk)
        t_full = time.monotonic()
        assert within(lambda: journal(tmp_path).get("writing") is False, 30)
        time.sleep(4.0)
        # served throughout, as if nothing had happened
        assert robot.longest_silence_s(t_full, time.monotonic()) < 1.0
        assert robot.answered_within(t_full, time.monotonic() - 1.0, 1.0) >= 0.95
        j = journal(tmp_path)
        assert j["failures"].get("journal", 0) >= 1 and j["not_journaled"] > 0
        filler.unlink()                     # room again
        assert within(lambda: journal(tmp_path).get("resumed", 0) >= 1, 30)
        assert journal(tmp_path)["writing"] is True
        time.sleep(2.0)
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(timeout=10)
        srv.stop()
        before = json.loads((tmp_path / "server" / "summary.json").read_text())
        kf_before = before["robots"]["r1"]["keyframes"]
        log = (tmp_path / "server.log").read_text(errors="replace")
        assert sum("state: writing the" in ln for ln in log.splitlines()) == 1
        assert "Traceback" not in log
        endpoint = srv.endpoint     # the same port again, so the robot finds it
        srv = ServerProcess(tmp_path, {**cfg, "bus": {"listen": [endpoint]}})
        srv.endpoint = endpoint
        srv.client().close()
        assert within(lambda: json.loads((tmp_path / "server" / "summary.json").read_text())
                      .get("resumed", {}).get("robots") == ["r1"], 60)
        after = json.loads((tmp_path / "server" / "summary.json").read_text())
        # the state written after the disk had room again holds what came while it was full
        assert after["robots"]["r1"]["keyframes"] >= kf_before
    finally:
        if robot is not None:
            robot.close()
        srv.stop()
