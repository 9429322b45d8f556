"""RPLIDAR: protocol bytes from the specification, resync, sweeps over a pty, unplugging."""

from __future__ import annotations

import math
import queue
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import serial

from robot_agent.backend import Sweep
from robot_agent.drivers import rplidar_protocol as proto
from robot_agent.drivers.fakes.rplidar import FakeRplidar, wall_room_mm
from robot_agent.drivers.rplidar import LidarDisconnected, Rplidar, RplidarSource
from schemas.messages import ranges_from_mm
from tests.conftest import ROOT
from tests.waiting import within

HALF_MM = 1500.0


class DtrRecordingSerial(serial.Serial):
    """pyserial on a pty, recording DTR changes (a pty has no modem lines to set)."""

    dtr_history: ClassVar[list[bool]] = []   # over all instances (the driver reopens ports)

    def _update_dtr_state(self) -> None:
        self.dtr_history.append(bool(self._dtr_state))


def room_with_gap(angle_deg: float) -> float:
    """A 3 m square room; no return between 100° and 110° (clockwise on the device)."""
    return 0.0 if 100.0 <= angle_deg < 110.0 else wall_room_mm(HALF_MM)(angle_deg)


def test_requests_descriptors_and_nodes_match_the_specification() -> None:
    assert proto.request(proto.CMD_SCAN) == bytes.fromhex("a5 20")
    assert proto.request(proto.CMD_STOP) == bytes.fromhex("a5 25")
    # set motor PWM 660: a5 f0 02 94 02 + XOR of all = a5^f0^02^94^02 = c1
    assert proto.request(proto.CMD_SET_MOTOR_PWM, (660).to_bytes(2, "little")) == \
        bytes.fromhex("a5 f0 02 94 02 c1")
    assert proto.Descriptor(5, 1, 0x81).encode() == bytes.fromhex("a5 5a 05 00 00 40 81")
    d = proto.parse_descriptor(bytes.fromhex("a5 5a 14 00 00 00 04"))
    assert (d.length, d.mode, d.data_type) == (20, 0, 4)
    # start node, quality 15, 90° (q6 5760 = 0x1680), 1000 mm (q2 4000 = 0x0fa0)
    node = bytes.fromhex("3d 01 2d a0 0f")
    assert proto.encode_node(True, 15, 90.0, 1000.0) == node
    n = proto.NodeParser().feed(node)
    assert (bool(n.start[0]), int(n.quality[0]), n.angle_deg[0], n.distance_mm[0]) == \
        (True, 15, 90.0, 1000.0)
    health = proto.parse_health(bytes((2, 0x34, 0x12)))
    assert (health.status, health.error_code) == ("error", 0x1234)
    with pytest.raises(proto.RplidarProtocolError, match="health status"):
        proto.parse_health(bytes((7, 0, 0)))
    with pytest.raises(proto.RplidarProtocolError, match="descriptor"):
        proto.parse_descriptor(bytes.fromhex("a5 5b 05 00 00 40 81"))


def random_nodes(rng: np.random.Generator, n: int) -> list[tuple[bool, int, float, float]]:
    return [(i % 100 == 0, int(rng.integers(0, 64)), float(rng.integers(0, 360 * 64)) / 64,
             float(rng.integers(0, 4 * 12000)) / 4) for i in range(n)]


def test_parser_resynchronises_after_corrupted_bytes() -> None:
    rng = np.random.default_rng(3)
    nodes = random_nodes(rng, 2000)
    stream = bytearray()
    sites = 0
    for k, node in enumerate(nodes):
        if k % 97 == 50:  # line noise: 1-7 random bytes, or a node cut short
            stream += rng.integers(0, 256, int(rng.integers(1, 8)), dtype=np.uint8).tobytes()
            sites += 1
        stream += proto.encode_node(*node)
    parser = proto.NodeParser()
    got: list[tuple[float, float]] = []
    for i in range(0, len(stream), 333):  # arbitrary chunking, as a serial port delivers
        out = parser.feed(bytes(stream[i:i + 333]))
        got += list(zip(out.angle_deg.tolist(), out.distance_mm.tolist(), strict=True))
    want = [(a, d) for _, _, a, d in nodes]
    recovered = set(got) & set(want)
    assert len(recovered) >= len(want) - 4 * sites     # a few nodes lost around each site
    assert len(got) - len(recovered) <= sites // 4     # rarely a spurious node
    assert parser.skipped_bytes > 0


def test_revolutions_start_at_the_flag_and_become_counter_clockwise_beams() -> None:
    a = proto.RevolutionAssembler(min_nodes=4)
    def nodes(angles: list[float], start: int | None) -> proto.Nodes:
        raw = b"".join(proto.encode_node(i == start, 10, x, 1000.0 + x)
                       for i, x in enumerate(angles))
        return proto.NodeParser().feed(raw)
    assert a.feed(nodes([300.0, 330.0], None), 0) == []          # partial turn: dropped
    assert a.feed(nodes([0.0, 90.0, 180.0, 270.0], 0), 100) == []
    revs = a.feed(nodes([359.0, 0.5, 45.0], 1), 200)
    assert len(revs) == 1 and revs[0].angle_deg.tolist() == [0.0, 90.0, 180.0, 270.0, 359.0]
    sweep = proto.to_sweep(revs[0], 360, 150, 12000)
    r = np.frombuffer(sweep.ranges_mm, "<u2")
    angles = sweep.angle_min_rad + sweep.angle_increment_rad * np.arange(360)
    def at(deg: float) -> int:
        return int(r[np.argmin(np.abs(np.remainder(angles - math.radians(deg) + math.pi,
                                                   2 * math.pi) - math.pi))])
    # clockwise on the device = negative in the robot frame
    assert (at(0), at(-90), at(180), at(90), at(1)) == (1000, 1090, 1180, 1270, 1359)
    assert np.count_nonzero(r) == 5


@pytest.fixture
def lidar(tmp_path: Path) -> Iterator[FakeRplidar]:
    fake = FakeRplidar(tmp_path / "rplidar", room_with_gap)
    yield fake
    fake.close()


def expected_mm(angles_rad: np.ndarray) -> np.ndarray:
    out = np.array([room_with_gap(math.degrees(-a) % 360.0) for a in angles_rad])
    return np.rint(out)


def check_sweep(sweep: Sweep, max_bad: int = 0) -> None:
    r = np.frombuffer(sweep.ranges_mm, "<u2").astype(float)
    angles = sweep.angle_min_rad + sweep.angle_increment_rad * np.arange(len(r))
    want = expected_mm(angles)
    assert len(r) == 360
    assert np.count_nonzero(np.abs(r - want) > 1.0) <= max_bad


def test_sweeps_over_a_pty_with_motor_on_noise_and_unplugging(lidar: FakeRplidar) -> None:
    sweeps: queue.Queue[Sweep] = queue.Queue()
    DtrRecordingSerial.dtr_history.clear()
    src = RplidarSource(str(lidar.link), reconnect_s=0.2, stall_s=1.0,
                        serial_factory=DtrRecordingSerial)
    src.start(sweeps.put)
    try:
        first = sweeps.get(timeout=5)
        check_sweep(first)
        assert src.info is not None and src.info.firmware == (1, 29)
        assert [c for c in lidar.requests[:4]] == [proto.CMD_STOP, proto.CMD_GET_INFO,
                                                  proto.CMD_GET_HEALTH, proto.CMD_SCAN]
        assert False in DtrRecordingSerial.dtr_history      # DTR low: motor on
        # no return between 100° and 110° clockwise -> about -100°..-110° in the robot frame
        ranges = ranges_from_mm(first.ranges_mm)
        assert np.isinf(ranges[75:80]).all() and np.isfinite(ranges[85:95]).all()

        lidar.inject(bytes.fromhex("a5 5a 13 ff 07") + b"\x00\x01\x02")   # line noise
        stamp = first.stamp_ns
        for _ in range(4):
            s = sweeps.get(timeout=5)
            assert s.stamp_ns > stamp
            stamp = s.stamp_ns
            check_sweep(s, max_bad=3)   # at most the nodes around the noise are lost
        assert within(lambda: src.counters["corrupt_bytes"] > 0, 2.0)

        lidar.unplug()
        assert within(lambda: not src.connected.is_set(), 3.0)
        assert src.counters["lidar_LidarDisconnected"] >= 1
        while not sweeps.empty():
            sweeps.get()
        lidar.plug()
        check_sweep(sweeps.get(timeout=5))
        assert src.connected.is_set() and src.counters["connects"] == 2
    finally:
        src.close()
    assert DtrRecordingSerial.dtr_history[-1] is True    # motor off at close


def test_a_missing_port_is_a_typed_error(tmp_path: Path) -> None:
    with pytest.raises(LidarDisconnected, match="cannot open"):
        Rplidar(str(tmp_path / "nothing"))


def test_health_error_is_reset(tmp_path: Path) -> None:
    fake = FakeRplidar(tmp_path / "rplidar", health=2)
    src = RplidarSource(str(fake.link), reconnect_s=0.2)
    sweeps: queue.Queue[Sweep] = queue.Queue()
    src.start(sweeps.put)
    try:
        sweeps.get(timeout=5)
        assert proto.CMD_RESET in fake.requests
    finally:
        src.close()
        fake.close()


@pytest.mark.e2e
def test_lidar_dump_prints_radians_metres_and_inf(lidar: FakeRplidar) -> None:
    out = subprocess.run([sys.executable, "-m", "mrslam.cli", "lidar-dump", "--port",
                          str(lidar.link), "--scans", "2"], cwd=ROOT, capture_output=True,
                         text=True, timeout=60, check=True)
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 2
    for line in lines:
        f = line.split()
        n = int(f[1])
        assert n == 360 and len(f) == 2 + 2 * n and int(f[0]) > 0
        angles = np.array(f[2::2], float)
        ranges = np.array(f[3::2], float)
        assert angles[0] == pytest.approx(-math.pi, abs=1e-5)
        assert np.allclose(np.diff(angles), 2 * math.pi / 360, atol=2e-5)
        finite = np.isfinite(ranges)
        assert 5 <= np.count_nonzero(~finite) <= 14          # the 10° gap
        exact = -math.pi + 2 * math.pi / n * np.arange(n)   # the printed angles, unrounded
        assert np.allclose(ranges[finite], expected_mm(exact[finite]) / 1000, atol=0.0015)


@pytest.mark.e2e
def test_lidar_dump_without_a_device_fails_in_one_line(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "mrslam.cli", "lidar-dump", "--port",
                          str(tmp_path / "ttyNONE"), "--scans", "1", "--timeout", "1"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "cannot open" in out.stderr and "Traceback" not in out.stderr
