"""Property test: whatever bytes arrive, decoding returns a valid message or a SchemaError."""

from __future__ import annotations

import os
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import MESSAGE_TYPES, SchemaError, decode, encode
from tests.examples import all_examples

EXAMPLES = all_examples()
#: mutations per message type: 200 in ``make test`` (derandomised, so the same every run);
#: ``MRSLAM_FUZZ_EXAMPLES=5000`` for a deeper search when the codec changes
FUZZ = settings(max_examples=int(os.environ.get("MRSLAM_FUZZ_EXAMPLES", "200")),
                deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])

leaf = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=40),
    st.binary(max_size=64),
)
value = st.recursive(leaf, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=12), inner, max_size=5)),
    max_leaves=12)


def _check(payload: bytes, cls: type[Any]) -> None:
    try:
        msg = decode(payload, cls)
    except SchemaError as e:
        assert e.message == cls.__name__
        return
    # accepted: it must be a valid message that re-encodes and decodes to itself
    assert isinstance(msg, cls)
    assert decode(encode(msg), cls) == msg


@pytest.mark.parametrize("name", sorted(MESSAGE_TYPES))
@FUZZ
@given(data=st.data())
def test_mutated_payloads(name: str, data: st.DataObject) -> None:
    cls = MESSAGE_TYPES[name]
    good = encode(EXAMPLES[name])
    kind = data.draw(st.sampled_from(["bytes", "truncate", "flip", "field", "drop", "random"]))
    if kind == "bytes":
        payload = data.draw(st.binary(max_size=256))
    elif kind == "truncate":
        payload = good[: data.draw(st.integers(0, len(good)))]
    elif kind == "flip":
        buf = bytearray(good)
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(buf) - 1))
            buf[i] = data.draw(st.integers(0, 255))
        payload = bytes(buf)
    else:
        fields = msgspec.msgpack.decode(good)
        if kind == "field":
            fields[data.draw(st.sampled_from(sorted(fields)))] = data.draw(value)
        elif kind == "drop":
            del fields[data.draw(st.sampled_from(sorted(fields)))]
        else:
            fields = data.draw(value)
        payload = msgspec.msgpack.encode(fields)
    _check(payload, cls)
