"""ROS 1 bags read record by record in file order (``server.offline.logs.bagfile``), for bags whose
index the rosbags library cannot read: the same messages as rosbags where it can, the
scan_tools demo bag where it cannot, and the intact part of a bag cut short."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from typer.testing import CliRunner

from mrslam.cli import app
from server.offline.logs.bagfile import deserializer, read_records
from server.offline.logs.rosbag import read_bag
from tests.bagbuild import FUSE, HOKUYO, Messages, Pose, Scan, real_scans, write_bag

needs_bags = pytest.mark.skipif(not FUSE.is_file(), reason="no ../shared/data/bags")


def built(path: Path, compression: str | None, n: int = 60) -> Path:
    """Real scans and odometry of the TurtleBot3 bag, rewritten in small chunks."""
    m = Messages(False)
    scans, poses = real_scans(n)
    msgs = [("/scan", "sensor_msgs/msg/LaserScan", s.stamp_ns, m.scan(s)) for s in scans]
    msgs += [("/odom", "nav_msgs/msg/Odometry", p.stamp_ns, m.odometry(p)) for p in poses]
    msgs.sort(key=lambda x: x[2])
    return write_bag(path, msgs, compression=compression, chunk_bytes=20_000)


@needs_bags
@pytest.mark.parametrize("compression", [None, "bz2", "lz4"])
def test_records_give_what_rosbags_gives(tmp_path: Path, compression: str | None) -> None:
    bag = built(tmp_path / "run.bag", compression)
    with AnyReader([bag]) as reader:
        theirs = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
    rec = read_records(bag, lambda ty: True)
    ours = [(rec.connections[k].topic, t, raw) for k, t, raw in rec.messages]
    assert ours == theirs and not rec.lost and len(ours) > 100
    de = deserializer(rec)
    _, _, raw = next(m for m in rec.messages if rec.connections[m[0]].topic == "/scan")
    assert de(raw, "sensor_msgs/msg/LaserScan").header.frame_id == "laser"


@needs_bags
def test_the_demo_bag_whose_index_rosbags_cannot_read(tmp_path: Path) -> None:
    """Its index data records give 20 bytes per entry where the entries are 12 bytes."""
    with pytest.raises(AssertionError), AnyReader([HOKUYO]):
        pass
    rec = read_records(HOKUYO, lambda ty: True)
    assert not rec.lost
    assert [c.topic for c in rec.connections.values()] == ["/scan"]
    assert len(rec.messages) == 360 and rec.counts == {0: 360}
    times = [t for _, t, _ in rec.messages]
    assert times == sorted(times)
    blog, info = read_bag(HOKUYO)
    assert info.reader.startswith("records in file order (its index cannot be read")
    assert len(blog.lasers) == 360 and info.odometry == "none: scan matching"
    first = blog.lasers[0]
    assert len(first.ranges_m) == 681
    assert math.degrees(first.angles_rad[-1] - first.angles_rad[0]) == pytest.approx(239.1, abs=0.5)
    # old bags name roslib/Header where the message says Header: read all the same
    assert first.stamp_text == "1282836370.970876375"
    assert abs(first.stamp_s - times[0] * 1e-9) < 0.5


@needs_bags
@pytest.mark.parametrize("compression", [None, "bz2"])
def test_a_bag_cut_short_maps_what_is_intact(tmp_path: Path, compression: str | None) -> None:
    whole = built(tmp_path / "whole.bag", compression, n=200)
    data = whole.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[:len(data) * 6 // 10])
    blog, info = read_bag(cut)
    full, _ = read_bag(whole)
    assert info.reader.startswith("records in file order") and info.lost
    n = len(blog.lasers)
    assert 0.4 * 200 < n < 200
    for a, b in zip(blog.lasers, full.lasers[:n], strict=True):   # the intact ones, the same
        assert a.stamp_text == b.stamp_text and np.array_equal(a.ranges_m, b.ranges_m)
        assert a.laser_pose is not None and b.laser_pose is not None
        assert np.allclose(a.laser_pose, b.laser_pose, atol=0.02)
    res = CliRunner().invoke(app, ["slam-log", str(cut), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["stream_truncated"] and summary["scans"] == n
    assert "the file ends at byte" in summary["bag"]["lost"][0]


def test_odometry_from_tf_of_an_old_bag(tmp_path: Path) -> None:
    """/tf as ROS 1 recorded it before tf2 (``tf/tfMessage``), with the laser mounted by
    /tf_static: each scan gets the laser's pose."""
    from rosbags.typesys import get_types_from_msg

    m = Messages(False)
    m.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                        "tf/msg/tfMessage"))
    msgs = [("/tf_static", "tf2_msgs/msg/TFMessage", 10**9,
             m.tf([("base_link", "laser", Pose(10**9, 0.2, 0.0, math.pi))]))]
    for k in range(10):
        t = 10**9 + k * 10**8
        tf = m.t["tf/msg/tfMessage"](transforms=m.tf(
            [("odom", "base_link", Pose(t, 0.1 * k, 0.0, 0.0))]).transforms)
        msgs.append(("/tf", "tf/msg/tfMessage", t, tf))
        msgs.append(("/scan", "sensor_msgs/msg/LaserScan", t,
                     m.scan(Scan(t + 5 * 10**7, -math.pi, 2 * math.pi / 360, 0.1, 10.0,
                                 np.full(360, 2.0, dtype=np.float32)))))
    bag = write_bag(tmp_path / "old.bag", msgs, store=m.store)
    blog, info = read_bag(bag)
    assert info.odometry == "/tf (base_link in odom)" and info.laser_pose_from == "/tf_static"
    assert len(blog.lasers) == 10
    # halfway between two transforms: 0.1 k + 0.05, and the laser 0.2 m ahead, turned round
    assert np.allclose(np.asarray(blog.lasers[3].laser_pose), [0.35 + 0.2, 0.0, math.pi])


@needs_bags
def test_garbage_between_chunks_is_passed_over(tmp_path: Path) -> None:
    """Bytes that are no record (a damaged disk block): reading resumes at the next chunk."""
    bag = built(tmp_path / "run.bag", None, n=60)
    data = bag.read_bytes()
    whole = read_records(bag, lambda ty: True)
    starts, pos = [], 13                       # after "#ROSBAG V2.0\n": records
    while pos < len(data):
        n = int.from_bytes(data[pos:pos + 4], "little")
        if b"op=\x05" in data[pos + 4:pos + 4 + n]:
            starts.append(pos)
        pos += 4 + n
        pos += 4 + int.from_bytes(data[pos:pos + 4], "little")
    assert len(starts) >= 3
    start = starts[2]                           # the third chunk
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(data[:start] + bytes(range(256)) * 2 + data[start:])
    rec = read_records(damaged, lambda ty: True)
    assert rec.messages == whole.messages
    assert len(rec.lost) == 1 and rec.lost[0].startswith(f"bytes {start}-{start + 512}")
    blog, info = read_bag(damaged)
    assert info.reader.startswith("records in file order") and len(blog.lasers) == 60
