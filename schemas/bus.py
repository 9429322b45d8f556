"""A thin typed layer over one Zenoh session.

The server opens its session in router mode and listens; agents, the simulator and users'
tools open client sessions that connect to it. Payloads are the codec's msgpack bytes. A payload
that does not decode is counted and logged, never passed on, and never raised into Zenoh's
threads; neither is an exception from a subscriber's callback.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

from schemas.codec import decode, encode
from schemas.errors import SchemaError
from schemas.messages import Message

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)
Mode = Literal["router", "client", "peer"]


class BusError(RuntimeError):
    """The Zenoh session could not be opened or used (bad endpoint, router unreachable...)."""


@dataclass
class BusStats:
    """Counters a process reports in its status and summary."""

    published: Counter[str] = field(default_factory=Counter)
    received: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)
    callback_errors: Counter[str] = field(default_factory=Counter)
    last_error: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "published": dict(self.published), "received": dict(self.received),
            "rejected": dict(self.rejected), "callback_errors": dict(self.callback_errors),
            "last_error": self.last_error,
        }


def zenoh_config(mode: Mode, listen: Iterable[str] = (), connect: Iterable[str] = (),
                 config_file: str | None = None, multicast_scouting: bool = False,
                 connect_timeout_ms: int | None = None) -> Any:
    """A ``zenoh.Config``: optional json5 file (TLS, access control) plus our settings."""
    import zenoh

    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if connect_timeout_ms is not None:
        conf.insert_json5("connect/timeout_ms", json.dumps(connect_timeout_ms))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    return conf


class Bus:
    """One Zenoh session with typed publish/subscribe, liveliness and queryables."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.stats = BusStats()
        self._publishers: dict[str, Any] = {}
        self._handles: list[Any] = []
        self._lock = threading.Lock()
        self._closed = False

    @classmethod
    def open(cls, mode: Mode, listen: Iterable[str] = (), connect: Iterable[str] = (),
             config_file: str | None = None, connect_timeout_ms: int | None = None) -> Bus:
        import zenoh

        zenoh.init_log_from_env_or("error")
        conf = zenoh_config(mode, listen, connect, config_file,
                            connect_timeout_ms=connect_timeout_ms)
        try:
            return cls(zenoh.open(conf))
        except zenoh.ZError as e:
            where = ", ".join(list(listen) + list(connect)) or "default endpoints"
            raise BusError(f"cannot open a Zenoh {mode} session on {where}: {e}") from None

    # -- publishing -------------------------------------------------------------------------
    def publish(self, key: str, msg: Message, *, block: bool = False) -> None:
        """Send ``msg`` on ``key``. When the link is congested, drop (default) or wait."""
        pub = self._publishers.get(key)
        if pub is None:
            import zenoh

            cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
            with self._lock:
                pub = self._publishers.get(key)
                if pub is None:
                    pub = self.session.declare_publisher(key, congestion_control=cc)
                    self._publishers[key] = pub
        pub.put(encode(msg))
        self.stats.published[type(msg).__name__] += 1

    def wait_for_subscribers(self, key: str, timeout_s: float = 5.0) -> bool:
        """Wait until a subscriber somewhere matches ``key``; False if none does in time.

        A client learns of subscriptions from its router, and until it has, what it publishes
        on ``key`` goes nowhere. A program whose first messages matter (a test, a one-shot
        command) waits here rather than sleeping for a guessed time.
        """
        pub = self.session.declare_publisher(key)
        try:
            deadline = time.monotonic() + timeout_s
            while not pub.matching_status.matching:
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.01)
            return True
        finally:
            pub.undeclare()

    # -- subscribing ------------------------------------------------------------------------
    def subscribe(self, key: str, cls: type[M], callback: Callable[[str, M], None]) -> Any:
        """Call ``callback(key, msg)`` for every valid ``cls`` on ``key`` (wildcards allowed)."""
        name = cls.__name__

        def on_sample(sample: Any) -> None:
            k = str(sample.key_expr)
            try:
                msg = decode(sample.payload.to_bytes(), cls)
            except SchemaError as e:
                self._reject(name, k, e)
                return
            self.stats.received[name] += 1
            try:
                callback(k, msg)
            except Exception as e:  # a broken handler must not kill Zenoh's thread
                self.stats.callback_errors[name] += 1
                self.stats.last_error = f"{k}: {type(e).__name__}: {e}"
                log.exception("handler for %s failed", k)

        sub = self.session.declare_subscriber(key, on_sample)
        self._handles.append(sub)
        return sub

    def subscribe_raw(self, key: str, callback: Callable[[str, bytes], None]) -> Any:
        """Call ``callback(key, payload)`` with undecoded payloads (recorders, byte counters)."""

        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:
                self.stats.callback_errors["raw"] += 1
                log.exception("raw handler for %s failed", sample.key_expr)

        sub = self.session.declare_subscriber(key, on_sample)
        self._handles.append(sub)
        return sub

    def _reject(self, name: str, key: str, err: SchemaError) -> None:
        self.stats.rejected[name] += 1
        self.stats.last_error = f"{key}: {err}"
        n = self.stats.rejected[name]
        if n <= 10 or n % 1000 == 0:  # logged, but a flood of garbage cannot flood the log
            log.warning("rejected message #%d on %s: %s", n, key, err)

    # -- liveliness -------------------------------------------------------------------------
    def declare_alive(self, key: str) -> Any:
        token = self.session.liveliness().declare_token(key)
        self._handles.append(token)
        return token

    def watch_alive(self, pattern: str, callback: Callable[[str, bool], None]) -> Any:
        """Call ``callback(key, alive)`` when a token matching ``pattern`` appears or vanishes.

        Tokens that exist already are reported on declaration.
        """
        import zenoh

        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
            except Exception:
                log.exception("liveliness handler for %s failed", sample.key_expr)

        sub = self.session.liveliness().declare_subscriber(pattern, on_sample, history=True)
        self._handles.append(sub)
        return sub

    # -- queries ----------------------------------------------------------------------------
    def serve(self, key: str, provide: Callable[[], Iterable[Message]]) -> Any:
        """Answer ``get(key)`` with the messages ``provide()`` returns (e.g. the latest map)."""

        def on_query(query: Any) -> None:
            try:
                for msg in provide():
                    query.reply(key, encode(msg))
            except Exception as e:
                log.exception("queryable %s failed", key)
                query.reply_err(f"{type(e).__name__}: {e}".encode())

        q = self.session.declare_queryable(key, on_query)
        self._handles.append(q)
        return q

    def get(self, key: str, cls: type[M], timeout_s: float = 2.0) -> list[M]:
        """Query ``key``; valid replies decoded, invalid ones counted and dropped."""
        out: list[M] = []
        for reply in self.session.get(key, timeout=timeout_s):
            if reply.ok is None:
                self.stats.last_error = f"{key}: error reply"
                continue
            try:
                out.append(decode(reply.ok.payload.to_bytes(), cls))
            except SchemaError as e:
                self._reject(cls.__name__, key, e)
        return out

    # -- lifetime ---------------------------------------------------------------------------
    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for h in reversed(self._handles):
            with contextlib.suppress(Exception):  # already gone with the session
                h.undeclare()
        self._publishers.clear()
        self.session.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def free_local_endpoint() -> str:
    """``tcp/127.0.0.1:<port>`` on a port that is free right now (tests, demo)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"
