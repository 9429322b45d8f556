"""What a recording's channels carry: each bus key's message type, its JSON Schema, and the
stamp read from a payload's header without decoding the rest."""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache

import msgspec

from schemas import keys
from schemas.export import schema_of

#: MCAP encodings of the wire channels: msgpack payloads described by JSON Schemas.
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "mrslam."


class _Header(msgspec.Struct):
    """The fields every message starts with; the rest of the map is skipped unread."""

    stamp_ns: int = 0
    seq: int = 0


_header_decoder = msgspec.msgpack.Decoder(_Header)


@dataclass(frozen=True)
class ChannelKind:
    """The message type on a key (``None``: a key no message type is defined for)."""

    type_name: str | None

    @property
    def schema_name(self) -> str:
        return f"{SCHEMA_PREFIX}{self.type_name}" if self.type_name else ""

    def schema_bytes(self) -> bytes:
        return schema_json(self.type_name) if self.type_name else b""


def kind_of(key: str) -> ChannelKind:
    return ChannelKind(keys.message_type_name(key))


@cache
def schema_json(type_name: str) -> bytes:
    """The message type's JSON Schema, as exported to ``schemas/json/``."""
    return json.dumps(schema_of(type_name), sort_keys=True).encode()


def type_name_of_schema(schema_name: str) -> str | None:
    """``mrslam.Scan`` -> ``Scan``; other schema names -> None."""
    if schema_name.startswith(SCHEMA_PREFIX):
        return schema_name[len(SCHEMA_PREFIX):] or None
    return None


def header_of(payload: bytes) -> tuple[int, int] | None:
    """``(stamp_ns, seq)`` of a payload, or None when it is not a message map with valid ones."""
    try:
        h = _header_decoder.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
    if not (0 <= h.stamp_ns < 2**63 and 0 <= h.seq < 2**63):
        return None
    return h.stamp_ns, h.seq
