"""Foxglove live: the run's Foxglove channels served over the SDK's WebSocket server.

The same channels as a recording's (``recording.foxglove``), so a layout made on a recording
works on a running fleet: open Foxglove, "Open connection", ``ws://127.0.0.1:PORT``. The server
listens on loopback unless told otherwise; reach it from another machine through an SSH tunnel
rather than opening the port.
"""

from __future__ import annotations

import logging
import threading

import foxglove

from recording.channels import kind_of
from recording.foxglove import MESSAGE_ENCODING, Converted, FoxgloveView, schema_of
from schemas.errors import SchemaError

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"


class FoxgloveLiveError(RuntimeError):
    """The WebSocket server could not start (port taken, bad address)."""

    user_error = True


class FoxgloveLive:
    """A WebSocket server with one channel per Foxglove topic, created as topics appear.

    ``add`` takes wire messages (it keeps its own frame tree); ``publish`` takes messages
    already converted (a recorder that converts for its file anyway). Thread-safe.
    """

    def __init__(self, port: int, host: str = DEFAULT_HOST, name: str = "mrslam") -> None:
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port,
                                                context=self.context)
        except Exception as e:   # the SDK raises its own error types from Rust
            raise FoxgloveLiveError(f"Foxglove WebSocket server on {host}:{port}: {e}") from e
        self.host = host
        self.view = FoxgloveView()
        self._channels: dict[str, foxglove.Channel] = {}
        self._lock = threading.Lock()
        self.published = 0
        self.errors = 0
        log.info("Foxglove live on ws://%s:%d", host, self.port)

    @property
    def port(self) -> int:
        return int(self.server.port)

    def add(self, key: str, payload: bytes) -> None:
        """Convert one wire message and publish what Foxglove draws of it."""
        with self._lock:
            try:
                converted = self.view.convert(kind_of(key).type_name, payload)
            except (SchemaError, ValueError) as e:
                self.errors += 1
                log.debug("no Foxglove view of %s: %s", key, e)
                return
            self._publish(converted, None)

    def publish(self, converted: list[Converted], log_time_ns: int | None = None) -> None:
        with self._lock:
            self._publish(converted, log_time_ns)

    def _publish(self, converted: list[Converted], log_time_ns: int | None) -> None:
        for topic, msg in converted:
            ch = self._channels.get(topic)
            if ch is None:
                ch = self._channels[topic] = foxglove.Channel(
                    topic, schema=schema_of(msg), message_encoding=MESSAGE_ENCODING,
                    context=self.context)
            ch.log(msg.encode(), log_time=log_time_ns)
            self.published += 1

    def close(self) -> None:
        self.server.stop()

    def __enter__(self) -> FoxgloveLive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
