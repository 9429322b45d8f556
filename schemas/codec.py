"""Encode and decode messages; every decoding failure becomes a SchemaError."""

from __future__ import annotations

import re
from typing import Any, TypeVar

import msgspec

from schemas.errors import SchemaError
from schemas.messages import (
    Event,
    MapUpdate,
    Message,
    RobotStates,
    RobotStatus,
    Scan,
    TagDetections,
    VelocityCommand,
)
from schemas.sim import (
    SimClock,
    SimGroundTruth,
    SimImage,
    SimLidar,
    SimMotorCommand,
    SimOdometry,
    SimStepAck,
)

M = TypeVar("M", bound=Message)

#: Every top-level message type, by name.
MESSAGE_TYPES: dict[str, type[Message]] = {
    t.__name__: t
    for t in (
        Scan, TagDetections, RobotStatus, VelocityCommand, MapUpdate, RobotStates, Event,
        SimClock, SimLidar, SimOdometry, SimImage, SimMotorCommand, SimStepAck, SimGroundTruth,
    )
}

_encoder = msgspec.msgpack.Encoder()
_decoders: dict[type[Any], msgspec.msgpack.Decoder[Any]] = {}
_PATH = re.compile(r" - at `\$\.?([^`]*)`$")
_MISSING = re.compile(r"^Object missing required field `([^`]*)`")
_POST_INIT = re.compile(r"^([A-Za-z_][\w.]*): (.*)$", re.S)


def encode(msg: Message) -> bytes:
    return _encoder.encode(msg)


def decode(payload: bytes | bytearray | memoryview, cls: type[M]) -> M:
    """Decode ``payload`` as a ``cls``; raise SchemaError naming the message and field."""
    dec = _decoders.get(cls)
    if dec is None:
        dec = _decoders[cls] = msgspec.msgpack.Decoder(cls)
    try:
        return dec.decode(payload)
    except msgspec.ValidationError as e:
        raise _schema_error(cls.__name__, str(e)) from None
    except msgspec.DecodeError as e:
        raise SchemaError(cls.__name__, "", f"not a msgpack message ({e})") from None
    except (ValueError, TypeError, OverflowError, RecursionError, MemoryError) as e:
        raise SchemaError(cls.__name__, "", f"{type(e).__name__}: {e}") from None


def _schema_error(name: str, text: str) -> SchemaError:
    """Turn msgspec's error text (``reason - at `$.a[0].b```) into a SchemaError."""
    path = ""
    m = _PATH.search(text)
    if m:
        path = re.sub(r"\[(\d+)\]", r".\1", m.group(1)).lstrip(".")
        text = text[: m.start()]
    field, reason = "", text
    missing = _MISSING.match(text)
    inner = _POST_INIT.match(text)
    if missing:
        field, reason = missing.group(1), "missing required field"
    elif inner and not text.startswith(("Expected", "Object")):
        # raised by a __post_init__ check, which names its own field
        field, reason = inner.group(1), inner.group(2)
    return SchemaError(name, ".".join(p for p in (path, field) if p), reason)
