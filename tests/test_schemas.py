"""Messages: round trips, quantisation, validation errors, JSON Schema drift."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from schemas import MESSAGE_TYPES, NO_RETURN_MM, SchemaError, decode, encode, keys
from schemas.export import JSON_DIR, render_all
from tests.examples import all_examples, scan

EXAMPLES = all_examples()


def test_every_message_type_has_an_example_and_a_key() -> None:
    assert set(EXAMPLES) == set(MESSAGE_TYPES)
    assert set(keys.KEY_TEMPLATES) == set(MESSAGE_TYPES)


@pytest.mark.parametrize("name", sorted(MESSAGE_TYPES))
def test_round_trip(name: str) -> None:
    msg = EXAMPLES[name]
    assert decode(encode(msg), MESSAGE_TYPES[name]) == msg


@pytest.mark.parametrize("name", sorted(MESSAGE_TYPES))
def test_wrong_schema_version_is_rejected(name: str) -> None:
    fields = msgspec.structs.asdict(EXAMPLES[name])
    fields["schema_version"] = 999
    with pytest.raises(SchemaError) as err:
        decode(msgspec.msgpack.encode(fields), MESSAGE_TYPES[name])
    assert err.value.message == name and err.value.field == "schema_version"


def test_scan_quantisation_and_no_return() -> None:
    s = scan()
    r = s.ranges_m()
    assert len(r) == 400 == s.n_beams
    assert np.all(np.isinf(r[::37]))
    assert np.frombuffer(s.ranges_mm, "<u2")[0] == NO_RETURN_MM
    finite = np.isfinite(r)
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.05, 10.0, 400)
    assert np.max(np.abs(r[finite] - truth[finite])) <= 0.0005 + 1e-12
    # NaN, inf, negative and beyond-range readings never reach the wire as numbers
    mm = np.frombuffer(msgspec.msgpack.decode(encode(s))["ranges_mm"], "<u2")
    assert mm.dtype == np.uint16
    from schemas import quantise_ranges_mm
    q = np.frombuffer(quantise_ranges_mm(np.array([np.nan, -1.0, 0.01, 12.0, 0.0004, 3.2]),
                                         0.0, 10.0), "<u2")
    assert list(q) == [0, 0, 10, 0, 1, 3200]


def test_400_beam_scan_fits_in_1000_bytes() -> None:
    assert len(encode(scan(robot_id="robot_12", seq=2**40))) <= 1000


@pytest.mark.parametrize(("field", "value", "expect_field"), [
    ("ranges_mm", b"\x01\x02\x03", "ranges_mm"),
    ("ranges_mm", b"", "ranges_mm"),
    ("odom_pose", [1.0, math.nan, 0.0], "odom_pose.1"),
    ("odom_pose", [1.0, 2.0], "odom_pose"),
    ("angle_increment_rad", 0.0, "angle_increment_rad"),
    ("range_max_mm", 10, "range_max_mm"),
    ("robot_id", "r1/../r2", "robot_id"),
    ("stamp_ns", -5, "stamp_ns"),
    ("seq", "seven", "seq"),
])
def test_scan_field_errors_name_the_field(field: str, value: object, expect_field: str) -> None:
    fields = msgspec.structs.asdict(scan())
    fields[field] = value
    with pytest.raises(SchemaError) as err:
        decode(msgspec.msgpack.encode(fields), MESSAGE_TYPES["Scan"])
    assert err.value.message == "Scan"
    assert err.value.field == expect_field


def test_missing_nested_field_is_named() -> None:
    raw = msgspec.msgpack.decode(encode(EXAMPLES["TagDetections"]))
    del raw["detections"][0]["range_m"]
    with pytest.raises(SchemaError) as err:
        decode(msgspec.msgpack.encode(raw), MESSAGE_TYPES["TagDetections"])
    assert err.value.field == "detections.0.range_m"


def test_map_cells_must_match_dimensions() -> None:
    raw = msgspec.msgpack.decode(encode(EXAMPLES["MapUpdate"]))
    raw["width"] += 1
    with pytest.raises(SchemaError) as err:
        decode(msgspec.msgpack.encode(raw), MESSAGE_TYPES["MapUpdate"])
    assert err.value.field == "cells"
    grid = EXAMPLES["MapUpdate"].grid()  # type: ignore[attr-defined]
    assert grid.shape == (40, 60) and grid[9, 20] == 100 and grid[0, 0] == -1


def test_garbage_and_truncation_raise_schema_error() -> None:
    payload = encode(scan())
    for bad in (b"", b"\xc1", b"garbage", payload[: len(payload) // 2], payload + b"\x00"):
        with pytest.raises(SchemaError):
            decode(bad, MESSAGE_TYPES["Scan"])


def test_json_schemas_are_up_to_date() -> None:
    """Fails when a message changed without `make schemas` (python -m schemas.export)."""
    files = render_all()
    on_disk = {p.name: p.read_text() for p in JSON_DIR.glob("*.json")}
    assert on_disk == files


def test_keys() -> None:
    assert keys.robot_scan("r1") == "mrslam/robot/r1/scan"
    assert keys.robot_id_of("mrslam/robot/r7/cmd_vel") == "r7"
    assert keys.robot_id_of("mrslam/sim/robot/r2/lidar") == "r2"
    assert keys.robot_id_of("mrslam/server/map") is None
    assert keys.message_type_name(keys.sim_ack("r3")) == "SimStepAck"
    assert keys.message_type_name("mrslam/robot/r1/unknown") is None
    with pytest.raises(ValueError):
        keys.robot_scan("r1/*")
