"""MCAP recordings as files: round trips, channel schemas, damaged files (the Foxglove channels
beside the wire ones: tests/test_foxglove_channels.py)."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import pytest
from mcap.reader import make_reader

from recording.reader import RecordingError, read_recording
from recording.writer import Compression, McapRecorder
from schemas import RobotStatus, decode, encode, keys
from tests.examples import STAMP, all_examples, scan

T0 = 5_000_000_000  # sim-time stamps, 100 ms apart


def robot_stream(n_scans: int, robots: tuple[str, ...] = ("r1", "r2")) -> list[tuple[str, bytes]]:
    """Scans and statuses of several robots, 10 Hz, interleaved as they would arrive."""
    out: list[tuple[str, bytes]] = []
    for k in range(n_scans):
        for i, rid in enumerate(robots):
            s = scan(rid, seq=k, seed=k * 7 + i)
            s = msgspec.structs.replace(s, stamp_ns=T0 + k * 100_000_000 + i)
            out.append((keys.robot_scan(rid), encode(s)))
            if k % 10 == 0:
                st = RobotStatus(robot_id=rid, seq=k, stamp_ns=T0 + k * 100_000_000 + 5,
                                 state="ok")
                out.append((keys.robot_status(rid), encode(st)))
    return out


def write(path: Path, stream: list[tuple[str, bytes]], compression: Compression = "zstd",
          chunk_size: int = 1 << 20, flush_every: int = 0, foxglove: bool = False) -> None:
    with McapRecorder(path, compression, foxglove, chunk_size=chunk_size) as rec:
        for i, (key, payload) in enumerate(stream):
            rec.add(key, payload, receive_ns=10**18 + i)
            if flush_every and (i + 1) % flush_every == 0:
                rec.flush()


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_every_message_type_round_trips_byte_for_byte(tmp_path: Path,
                                                      compression: Compression) -> None:
    examples = all_examples()
    stream = [(keys.KEY_TEMPLATES[name].replace("<id>", "r1"), encode(msg))
              for name, msg in examples.items()]
    write(tmp_path / "all.mcap", stream, compression)
    rec = read_recording(tmp_path / "all.mcap")
    assert rec.report.intact and rec.report.expected_messages == len(stream)
    got = {m.topic: m for m in rec.messages}
    for (key, payload), name in zip(stream, examples, strict=True):
        m = got[key]
        assert m.data == payload and m.type_name == name
        assert m.log_time_ns == m.publish_time_ns == examples[name].stamp_ns
        assert decode(m.data, type(examples[name])) == examples[name]


def test_the_mcap_library_reads_channels_schemas_and_stamps(tmp_path: Path) -> None:
    stream = robot_stream(30)
    write(tmp_path / "run.mcap", stream, flush_every=13)
    with (tmp_path / "run.mcap").open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == len(stream)
        topics = {c.topic for c in summary.channels.values()}
        assert topics == {keys.robot_scan("r1"), keys.robot_scan("r2"),
                          keys.robot_status("r1"), keys.robot_status("r2")}
        for ch in summary.channels.values():
            schema = summary.schemas[ch.schema_id]
            assert ch.message_encoding == "msgpack" and schema.encoding == "jsonschema"
            doc = json.loads(schema.data)
            assert doc["x-mrslam-key"] == keys.KEY_TEMPLATES[schema.name.split(".", 1)[1]]
        times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=True)]
    assert times == sorted(t for t in times) and times[0] == T0
    assert len(times) == len(stream)


def test_payloads_without_a_stamp_are_kept_at_their_receive_time(tmp_path: Path) -> None:
    good = scan(seq=1)
    with McapRecorder(tmp_path / "odd.mcap", foxglove_channels=False) as rec:
        rec.add(keys.robot_scan("r1"), b"\xc1garbage", receive_ns=100)  # before any stamp
        rec.add(keys.robot_scan("r1"), encode(good), receive_ns=1_000)
        rec.add(keys.robot_scan("r1"), b"not msgpack at all", receive_ns=1_250)
        rec.add("mrslam/somewhere/else", encode(good), receive_ns=1_300)
        assert sum(rec.stats.undecodable.values()) == 2 and rec.stats.unknown_keys == 1
    msgs = read_recording(tmp_path / "odd.mcap").messages
    assert [m.log_time_ns for m in msgs] == [0, STAMP, STAMP + 250, STAMP]
    assert msgs[2].data == b"not msgpack at all"
    assert msgs[3].type_name is None


# -- damaged files ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """A finished recording of 2 robots × 200 scans in ~20 chunks (flushed as the recorder
    does every second)."""
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    stream = robot_stream(200)
    write(path, stream, flush_every=21)
    return path, len(stream)


@pytest.mark.parametrize("fraction", [0.15, 0.5, 0.83, 0.995])
def test_a_truncated_recording_gives_back_its_complete_chunks(
        recorded: tuple[Path, int], tmp_path: Path, fraction: float) -> None:
    path, total = recorded
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * fraction)])
    rec = read_recording(cut)
    r = rec.report
    assert not r.finished and not r.intact
    assert 0 < r.messages <= total
    assert r.messages >= (fraction - 0.12) * total  # at most about one chunk is lost
    if fraction > 0.99:  # only the summary was cut off
        assert r.messages == total
    full = {(m.topic, m.log_time_ns): m.data for m in read_recording(path).messages}
    assert all(full[(m.topic, m.log_time_ns)] == m.data for m in rec.messages)
    assert r.messages + r.counted_lost <= total


def test_flipped_bytes_in_the_middle_cost_only_their_chunk(recorded: tuple[Path, int],
                                                           tmp_path: Path) -> None:
    path, total = recorded
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    for i in range(mid, mid + 64, 7):
        data[i] ^= 0xA5
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    r = read_recording(bad).report
    assert r.finished and not r.intact and r.damaged_chunks == 1
    assert r.expected_messages == total
    assert total * 0.85 < r.messages < total
    assert r.messages + r.unreadable_messages == total


def test_a_broken_record_frame_is_skipped_to_the_next_chunk(recorded: tuple[Path, int],
                                                            tmp_path: Path) -> None:
    """Clobbered record headers (no summary to help): the scan finds the next chunk itself."""
    path, total = recorded
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    second = summary.chunk_indexes[1].chunk_start_offset
    data = bytearray(path.read_bytes())
    data[second:second + 9] = b"\xff" * 9
    cut = tmp_path / "frames.mcap"
    cut.write_bytes(bytes(data[:int(len(data) * 0.9)]))
    r = read_recording(cut).report
    assert r.skipped_bytes > 0
    assert total * 0.6 < r.messages < total


def test_unreadable_files_raise_a_typed_error(tmp_path: Path,
                                              recorded: tuple[Path, int]) -> None:
    (tmp_path / "empty.mcap").write_bytes(b"")
    (tmp_path / "text.mcap").write_text("stamp_ns,x_m,y_m\n1,2,3\n")
    (tmp_path / "head.mcap").write_bytes(recorded[0].read_bytes()[:60])
    for name, words in (("empty.mcap", "empty"), ("text.mcap", "not an MCAP"),
                        ("head.mcap", "no readable message"), ("missing.mcap", "cannot read")):
        with pytest.raises(RecordingError, match=words):
            read_recording(tmp_path / name)


def test_recording_imports_only_schemas_of_ours() -> None:
    import ast

    ours = {"schemas", "factors", "server", "robot_agent", "sim", "mrslam", "recording"}
    folder = Path(__file__).resolve().parent.parent / "recording"
    used: set[str] = set()
    for f in folder.glob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                used |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module:
                used.add(node.module.split(".")[0])
    assert used & ours == {"schemas", "recording"}
