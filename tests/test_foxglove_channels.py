"""The Foxglove channels of a recording: each message decodes with the schema the Foxglove SDK
provides, beams without a return are not drawn, and the frames hang from one root once the
teams have merged. ``check_foxglove`` is also what the demo's end-to-end test runs on run.mcap."""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from foxglove import messages as fm
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, unknown_fields
from mcap.reader import make_reader

from recording.writer import McapRecorder
from schemas import Event, MapUpdate, RobotEstimate, RobotStates, Scan, decode, encode, keys
from schemas.se2 import compose
from tests.examples import STAMP, all_examples, scan


def _message_class(schema_name: str, schema_data: bytes) -> Any:
    """The protobuf class of ``schema_name`` built from the file's descriptor set alone."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    while pending:   # dependencies first, in whatever order the set lists them
        progress = False
        for f in list(pending):
            try:
                pool.Add(f)
            except TypeError:
                continue
            pending.remove(f)
            progress = True
        assert progress, f"descriptor set of {schema_name} does not resolve"
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def _roots(parent_of: dict[str, str], frames: set[str]) -> set[str]:
    roots = set()
    for f in frames:
        seen = {f}
        while f in parent_of and parent_of[f] not in seen:
            f = parent_of[f]
            seen.add(f)
        roots.add(f)
    return roots


def check_foxglove(path: Path) -> dict[str, Any]:
    """Read a recording's Foxglove channels and check them; returns the figures.

    Fails (AssertionError) when a channel's schema is not the SDK's, a message does not decode
    with it (or carries fields the schema does not know), or a scan's beams differ from the
    wire scan it was made from.
    """
    classes: dict[str, Any] = {}
    per_schema: Counter[str] = Counter()
    wire_scans: dict[tuple[str, int], np.ndarray] = {}
    fox_scans: list[tuple[str, int, list[float]]] = []
    tf_msgs: list[tuple[int, Any]] = []
    merges: list[int] = []
    drawn_frames: dict[str, str] = {}          # topic -> frame of its latest message
    scan_times: dict[str, list[int]] = defaultdict(list)
    with path.open("rb") as f:
        for schema, channel, m in make_reader(f).iter_messages(log_time_order=True):
            if channel.topic.startswith(f"{keys.ROOT}/"):
                if channel.topic.endswith("/scan"):
                    s = decode(m.data, Scan)
                    wire_scans[(s.robot_id, s.stamp_ns)] = s.ranges_m()
                elif channel.topic == keys.SERVER_EVENTS and \
                        decode(m.data, Event).kind == "merge":
                    merges.append(m.log_time)
                continue
            assert schema is not None and channel.message_encoding == "protobuf", channel.topic
            sdk = getattr(fm, schema.name.removeprefix("foxglove.")).get_schema()
            assert (schema.encoding, schema.data) == (sdk.encoding, sdk.data), schema.name
            cls = classes.get(schema.name) or classes.setdefault(
                schema.name, _message_class(schema.name, schema.data))
            msg = cls.FromString(m.data)
            assert len(unknown_fields.UnknownFieldSet(msg)) == 0, channel.topic
            per_schema[schema.name] += 1
            if schema.name == "foxglove.LaserScan":
                fox_scans.append((msg.frame_id, msg.timestamp.seconds * 10**9
                                  + msg.timestamp.nanos, list(msg.ranges)))
                scan_times[msg.frame_id].append(m.log_time)
            elif schema.name == "foxglove.FrameTransforms":
                tf_msgs.append((m.log_time, msg))
            if hasattr(msg, "frame_id"):
                drawn_frames[channel.topic] = msg.frame_id

    # no-return beams: +inf where the wire scan had none, the measured range elsewhere
    no_return = drawn_as_points = 0
    for rid, stamp, ranges in fox_scans:
        wire = wire_scans[(rid, stamp)]
        r = np.asarray(ranges)
        assert r.shape == wire.shape
        missing = ~np.isfinite(wire)
        assert np.all(np.isposinf(r[missing])), "a no-return beam is not +inf"
        assert np.allclose(r[~missing], wire[~missing])
        no_return += int(missing.sum())
        drawn_as_points += int(np.count_nonzero(np.isfinite(r[missing])))

    # a transform tree with every scan: the scan's own robot placed at the scan's stamp
    tf_at = defaultdict(list)
    for t, msg in tf_msgs:
        tf_at[t].append(msg)
    scans_without_tf = sum(
        1 for rid, times in scan_times.items() for t in times
        if not any(tr.child_frame_id == rid for msg in tf_at.get(t, []) for tr in msg.transforms))

    # roots of every frame drawn after the last merge: Foxglove keeps each frame's latest
    # transform across messages, so the tree at a message is all transforms up to it. A
    # robot whose first estimate has not come yet has an odometry frame with no parent: it
    # is not placed in any team yet (a merge in the first second can come before it), and
    # is not counted as a root of its own
    parent_of: dict[str, str] = {}
    after_merge: list[set[str]] = []
    lagging = 0   # single tree messages without the link (made before the merge arrived)
    unplaced = 0  # tree messages after the merge with a robot not yet placed
    for t, msg in tf_msgs:
        own = {tr.child_frame_id: tr.parent_frame_id for tr in msg.transforms}
        parent_of.update(own)
        if merges and t > merges[-1]:
            frames = set(parent_of) | set(drawn_frames.values())
            roots = _roots(parent_of, frames)
            waiting = {r for r in roots if r.endswith("/odom")}
            unplaced += bool(waiting)
            after_merge.append(roots - waiting)
            lagging += len(_roots(own, set(own) | set(drawn_frames.values()))) > 1

    def roots_of(msg: Any) -> set[str]:
        own = {tr.child_frame_id: tr.parent_frame_id for tr in msg.transforms}
        return _roots(own, set(own) | set(drawn_frames.values()))

    return {"messages": dict(per_schema), "scans": len(fox_scans),
            "no_return_beams": no_return, "no_return_drawn_as_points": drawn_as_points,
            "scans_without_transform": scans_without_tf, "merges": len(merges),
            "tree_messages_after_last_merge": len(after_merge),
            "single_tree_messages_without_the_link": lagging,
            "max_roots_after_last_merge": max((len(r) for r in after_merge), default=0),
            "tree_messages_with_a_robot_not_yet_placed": unplaced,
            "roots_at_end": sorted(roots_of(tf_msgs[-1][1])) if tf_msgs else []}


# -- a synthetic run: two robots, each its own team, then one merge --------------------------

T_T1_T2 = (2.0, -1.0, math.pi / 2)   # team t2's frame in t1's, as the merge found it


def two_teams_merge(path: Path) -> None:
    def states(stamp: int, merged: bool) -> RobotStates:
        r2 = (1.0, 0.5, 0.2)
        return RobotStates(stamp_ns=stamp, robots=[
            RobotEstimate(robot_id="r1", team_id="t1", pose=(0.5, 0.0, 0.1),
                          last_scan_stamp_ns=stamp),
            RobotEstimate(robot_id="r2", team_id="t1" if merged else "t2",
                          pose=tuple(compose(T_T1_T2, r2).tolist()) if merged else r2,
                          last_scan_stamp_ns=stamp + 1)])

    grid = all_examples()["MapUpdate"]
    assert isinstance(grid, MapUpdate)
    with McapRecorder(path, foxglove_channels=True) as rec:
        for k in range(30):
            t = STAMP + k * 100_000_000
            for i, rid in enumerate(("r1", "r2")):
                s = msgspec.structs.replace(scan(rid, seq=k, seed=k), stamp_ns=t + i,
                                            odom_pose=(0.01 * k, 0.0, 0.0))
                rec.add(keys.robot_scan(rid), encode(s))
            if k % 10 == 5:
                rec.add(keys.SERVER_ROBOTS, encode(states(t, merged=k > 15)))
                for team in ("t1",) if k > 15 else ("t1", "t2"):
                    rec.add(keys.SERVER_MAP, encode(msgspec.structs.replace(
                        grid, team_id=team, stamp_ns=t)))
            if k == 15:
                rec.add(keys.SERVER_EVENTS, encode(Event(
                    kind="merge", team_id="t1", robot_ids=["r1", "r2"], stamp_ns=t + 2,
                    message="t2 merged into t1 from 3 sightings", transform=T_T1_T2)))


@pytest.fixture(scope="module")
def merged_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("fox") / "run.mcap"
    two_teams_merge(path)
    return path


def test_every_channel_decodes_with_the_sdk_schema(merged_run: Path) -> None:
    got = check_foxglove(merged_run)
    assert set(got["messages"]) == {"foxglove.LaserScan", "foxglove.FrameTransforms",
                                    "foxglove.Grid", "foxglove.PoseInFrame",
                                    "foxglove.PosesInFrame", "foxglove.Log"}
    assert got["messages"]["foxglove.LaserScan"] == 60


def test_beams_without_a_return_are_not_points(merged_run: Path) -> None:
    got = check_foxglove(merged_run)
    assert got["no_return_beams"] == 60 * len(range(0, 400, 37))
    assert got["no_return_drawn_as_points"] == 0


def test_a_transform_tree_comes_with_every_scan(merged_run: Path) -> None:
    got = check_foxglove(merged_run)
    assert got["scans"] == 60 and got["scans_without_transform"] == 0


def test_after_the_merge_every_frame_hangs_from_one_root(merged_run: Path) -> None:
    got = check_foxglove(merged_run)
    assert got["merges"] == 1 and got["tree_messages_after_last_merge"] > 20
    assert got["max_roots_after_last_merge"] == 1 and got["roots_at_end"] == ["t1"]


def test_before_the_merge_the_teams_are_separate_trees(tmp_path: Path) -> None:
    """The check can fail: cut the run before the merge and there are two roots."""
    from recording.frames import FrameTree

    def root_of(frame: str) -> set[str]:   # per the tree's latest transforms
        return _roots({t.child: t.parent for t in tree.transforms(0)}, {frame})

    tree = FrameTree()
    tree.add_scan(msgspec.structs.replace(scan("r2"), stamp_ns=STAMP))
    tree.add_states(RobotStates(stamp_ns=STAMP, robots=[RobotEstimate(
        robot_id="r2", team_id="t2", pose=(1.0, 0.5, 0.2), last_scan_stamp_ns=STAMP)]))
    assert root_of("r2") == {"t2"}
    tree.add_event(Event(kind="merge", team_id="t1", robot_ids=["r1", "r2"], stamp_ns=STAMP,
                         message="t2 merged into t1", transform=T_T1_T2))
    assert root_of("r2") == {"t1"}
    tree.add_event(Event(kind="merge_undone", team_id="t1", robot_ids=["r1", "r2"],
                         stamp_ns=STAMP, message="t2 split from t1: sightings contradict"))
    assert root_of("r2") == {"t2"}


def test_the_tree_places_a_robot_where_the_server_estimated_it(merged_run: Path) -> None:
    """Chaining the last tree's transforms gives r2's estimate in t1 (after the merge), and
    its trajectory was carried into t1's frame."""
    from recording.foxglove import FoxgloveView

    view = FoxgloveView()
    with merged_run.open("rb") as f:
        for schema, channel, m in make_reader(f).iter_messages(log_time_order=True):
            if channel.topic.startswith(f"{keys.ROOT}/") and schema is not None:
                view.convert(schema.name.removeprefix("mrslam."), m.data)
    frames = view.frames
    by_child = {t.child: t for t in frames.transforms(0)}
    T = np.zeros(3)
    f = "r2"
    while f in by_child:
        T = compose(by_child[f].pose, T)
        f = by_child[f].parent
    assert f == "t1"
    r2_last = np.asarray(compose(T_T1_T2, (1.0, 0.5, 0.2)))
    # the estimate refers to the scan stamped t + 1; odometry moved on by later scans
    assert np.allclose(T[:2], r2_last[:2], atol=0.15)
    traj = frames.trajectories["r2"]
    assert frames.trajectory_frame["r2"] == "t1" and len(traj) == 3
    assert np.allclose(traj[0], compose(T_T1_T2, (1.0, 0.5, 0.2)))
