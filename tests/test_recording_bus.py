"""Recording and replaying on a real Zenoh loopback: the recorder as its own process stopped by
SIGTERM, replay timing and key filters, the command line's errors."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import pytest
from mcap.reader import make_reader

from recording.reader import read_recording
from recording.replay import run as replay
from recording.writer import McapRecorder
from schemas import RobotStatus, encode, keys
from schemas.bus import Bus
from schemas.config import BusConfig
from tests.examples import scan

ROOT = Path(__file__).resolve().parent.parent


def mrslam(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "mrslam", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


@pytest.mark.e2e
def test_recorder_process_writes_what_was_published_and_finishes_on_sigterm(
        tmp_path: Path, endpoint: str, router: Bus) -> None:
    out = tmp_path / "run.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "mrslam", "record", "--out", str(out),
                             "--connect", endpoint], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while not out.exists() and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""
            time.sleep(0.1)
        sent: list[tuple[str, bytes]] = []
        with Bus.open("client", connect=[endpoint]) as pub:
            for key in (keys.robot_scan("r1"), keys.robot_scan("r2"), keys.robot_status("r1")):
                assert pub.wait_for_subscribers(key, timeout_s=30), key
            for k in range(20):
                for rid in ("r1", "r2"):
                    s = msgspec.structs.replace(scan(rid, seq=k, seed=k),
                                                stamp_ns=10**9 + k * 10**8)
                    pub.publish(keys.robot_scan(rid), s, block=True)
                    sent.append((keys.robot_scan(rid), encode(s)))
            status = RobotStatus(robot_id="r1", stamp_ns=10**9 + 5 * 10**8, state="ok")
            pub.publish(keys.robot_status("r1"), status, block=True)
            sent.append((keys.robot_status("r1"), encode(status)))
            pub.session.put(keys.robot_tags("r1"), b"\x00garbage")
            time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
    rec = read_recording(out)
    assert rec.report.intact
    wire = [m for m in rec.messages if m.topic.startswith("mrslam/")]
    assert sorted((m.topic, m.data) for m in wire if m.type_name != "TagDetections") == \
        sorted(sent)
    garbage = [m for m in wire if m.topic == keys.robot_tags("r1")]
    assert len(garbage) == 1 and garbage[0].data == b"\x00garbage"
    assert sum(m.topic == "foxglove/robot/r2/scan" for m in rec.messages) == 20
    with out.open("rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta["mrslam.recorder"]["undecodable"] == "1"
    assert meta["mrslam.recorder"]["messages"] == str(len(sent) + 1)


def make_recording(path: Path) -> list[tuple[str, int]]:
    """2 s of two robots' scans at 10 Hz plus server output, with sim-time stamps."""
    expected = []
    with McapRecorder(path) as rec:
        for k in range(20):
            t = 3 * 10**9 + k * 10**8
            for rid in ("r1", "r2"):
                s = msgspec.structs.replace(scan(rid, seq=k, seed=k), stamp_ns=t)
                rec.add(keys.robot_scan(rid), encode(s))
                expected.append((keys.robot_scan(rid), t))
            rec.add(keys.SERVER_EVENTS, b"\x80")  # no stamp: at receive time
    return expected


def test_replay_keeps_order_and_timing_and_filters_keys(tmp_path: Path, endpoint: str,
                                                        router: Bus) -> None:
    path = tmp_path / "two.mcap"
    expected = make_recording(path)
    got: list[tuple[str, int, float]] = []
    lock = threading.Lock()

    def on_scan(key: str, msg: object) -> None:
        with lock:
            got.append((key, msg.stamp_ns, time.monotonic()))  # type: ignore[attr-defined]

    from schemas import Scan

    server_keys: list[str] = []
    router.subscribe(keys.ALL_SCANS, Scan, on_scan)
    router.subscribe_raw(f"{keys.ROOT}/server/**", lambda k, _: server_keys.append(k))
    summary = replay(path, BusConfig(connect=[endpoint]), speed=2.0,
                     only=["mrslam/robot/**"], linger_s=1.0)
    assert summary["published"] == len(expected) == summary["selected"]
    assert not server_keys  # filtered out
    per_robot = {rid: [s for k, s, _ in got if k == keys.robot_scan(rid)] for rid in ("r1", "r2")}
    for rid, stamps in per_robot.items():
        assert stamps == [t for k, t in expected if k == keys.robot_scan(rid)]
    span = got[-1][2] - got[0][2]
    assert 0.9 * 1.9 / 2 <= span < 1.9 / 2 + 1.5  # 1.9 s of stamps at twice the speed

    summary = replay(path, BusConfig(connect=[endpoint]), speed=0,
                     until_ns=3 * 10**9 + 10**8 + 10**6, linger_s=1.0)
    assert summary["by_type"] == {"Scan": 4, "Event": 2}


@pytest.mark.e2e
def test_command_line_errors_are_one_line(tmp_path: Path) -> None:
    (tmp_path / "bad.mcap").write_text("hello")
    r = mrslam("replay", str(tmp_path / "bad.mcap"), "--connect", "tcp/127.0.0.1:9")
    assert r.returncode == 2 and "not an MCAP file" in r.stderr
    r = mrslam("merge", "a.mcap", "b.mcap", "--out", str(tmp_path))
    assert r.returncode == 2 and "a.mcap: cannot read" in r.stderr


def test_recorder_leaves_out_excluded_keys(tmp_path: Path, endpoint: str, router: Bus) -> None:
    from recording.record import run as record

    out = tmp_path / "run.mcap"
    stop = threading.Event()
    result: dict[str, object] = {}
    t = threading.Thread(target=lambda: result.update(record(
        out, BusConfig(mode="client", connect=[endpoint]), stop=stop,
        exclude=("mrslam/robot/*/status",))))
    t.start()
    try:
        deadline = time.monotonic() + 30
        while not out.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        with Bus.open("client", connect=[endpoint]) as pub:
            assert pub.wait_for_subscribers(keys.robot_scan("r1"), timeout_s=30)
            for k in range(5):
                pub.publish(keys.robot_scan("r1"), msgspec.structs.replace(
                    scan("r1", seq=k, seed=k), stamp_ns=10**9 + k * 10**8), block=True)
                pub.publish(keys.robot_status("r1"), RobotStatus(
                    robot_id="r1", seq=k, stamp_ns=10**9 + k * 10**8, state="ok"), block=True)
            time.sleep(1.0)
    finally:
        stop.set()
        t.join(timeout=20)
    topics = [m.topic for m in read_recording(out).messages]
    assert topics.count(keys.robot_scan("r1")) == 5
    assert keys.robot_status("r1") not in topics
    assert result["excluded"] == 5
