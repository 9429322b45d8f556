"""The one error type of the wire layer."""

from __future__ import annotations


class SchemaError(ValueError):
    """A payload that is not a valid message of the expected type.

    ``message`` is the message type's name (e.g. ``"Scan"``), ``field`` the offending field as a
    dotted path (``"ranges_mm"``, ``"detections.0.range_m"``) or ``""`` when the payload as a
    whole is broken (garbage, truncated), and ``reason`` what is wrong with it.
    """

    def __init__(self, message: str, field: str, reason: str) -> None:
        self.message = message
        self.field = field
        self.reason = reason
        where = f"{message}.{field}" if field else message
        super().__init__(f"{where}: {reason}")
