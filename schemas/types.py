"""Constrained field types shared by the message definitions.

Every float on the wire is finite: the bounds below reject NaN and ±inf at decode time, so no
receiver ever has to check for them.
"""

from __future__ import annotations

import math
from typing import Annotated

import msgspec

SCHEMA_VERSION = 1

#: Scan ranges travel as unsigned millimetres; this value means "no return" (beam hit nothing
#: inside the sensor's range, or the reading was invalid). Never NaN on the wire.
NO_RETURN_MM = 0
MAX_RANGE_MM = 65535

#: Robot and team ids appear inside key expressions, so they may not contain ``/``, ``*``,
#: ``$``, ``?`` or ``#``.
ID_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"

RobotId = Annotated[str, msgspec.Meta(pattern=ID_PATTERN, description="robot id, e.g. 'r1'")]
TeamId = Annotated[str, msgspec.Meta(pattern=ID_PATTERN, description="team id")]
Seq = Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1, description="per-publisher sequence number")]
StampNs = Annotated[
    int, msgspec.Meta(ge=0, le=2**63 - 1, description="time of the data [ns], int64")
]
Version = Annotated[int, msgspec.Meta(ge=0, le=2**31, description="schema version")]

Metres = Annotated[float, msgspec.Meta(ge=-1e7, le=1e7, description="[m]")]
PositiveMetres = Annotated[float, msgspec.Meta(ge=0.0, le=1e4, description="[m], >= 0")]
Radians = Annotated[
    float, msgspec.Meta(ge=-2 * math.pi, le=2 * math.pi, description="[rad], |a| <= 2*pi")
]
Sigma = Annotated[float, msgspec.Meta(gt=0.0, le=1e4, description="standard deviation, > 0")]
Fraction = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
Finite = Annotated[float, msgspec.Meta(ge=-1e12, le=1e12)]

#: A planar pose (x [m], y [m], theta [rad]).
Pose2 = Annotated[
    tuple[Metres, Metres, Radians], msgspec.Meta(description="pose (x [m], y [m], theta [rad])")
]
