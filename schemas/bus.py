"""A thin typed layer over one Zenoh session.

The server opens its session in router mode and listens; agents, the simulator and users'
tools open client sessions that connect to it. Payloads are the codec's msgpack bytes. A payload
that does not decode is counted and logged, never passed on, and never raised into Zenoh's
threads; neither is an exception from a subscriber's callback.
"""

from __future__ import annotations

import contextlib
import ipaddress
import itertools
import json
import logging
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar

from schemas.codec import decode, encode
from schemas.errors import SchemaError
from schemas.keys import HOLDER_CHUNK
from schemas.messages import Message
from schemas.tlsfiles import tls_file_problems

if TYPE_CHECKING:
    from schemas.config import BusConfig

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)
Mode = Literal["router", "client", "peer"]

#: what a session accepts in one message by default [bytes]. Our largest messages are a
#: 640x480 camera frame (SimImage, 307 kB) and a team's map (MapUpdate: zlib int8 cells; a
#: 900x900 grid is 80-150 kB as maps look, 0.7-0.8 MB if every cell were noise). It is given
#: to Zenoh (``transport/link/rx/max_message_size``), whose link drops every larger message
#: while shared memory is off (with it on, 1.10 dropped only the first: later ones crossed as
#: shared-memory descriptors, see SHARED_MEMORY). ``Bus``'s subscribers also drop a larger
#: payload, counted as rejected, before copying or decoding it, in case a session's link
#: takes more.
DEFAULT_MAX_MESSAGE_SIZE = 1_572_864
#: liveliness tokens ``<key>/zid/<session id>`` say which session holds ``<key>``'s token
_RUST_SOURCE = re.compile(r"\s*\bat\s+/\S+\.rs:\d+\.?")


class BusError(RuntimeError):
    """The Zenoh session could not be opened or used (bad endpoint, router unreachable...)."""


_PARSE_AT = re.compile(r"-->\s*(\d+):(\d+)")
_PARSE_WHAT = re.compile(r"^\s*=\s*(.+)$", re.MULTILINE)
_DEBUG_MSG = re.compile(r'\bmsg:\s*"((?:[^"\\]|\\.)*)"')   # Json5Err(Message { msg: "..." })


def zenoh_message(err: BaseException) -> str:
    """Zenoh's error text on one line, without the Rust source paths it carries (a json5
    parse error becomes ``what at line L, column C``)."""
    text = _RUST_SOURCE.sub("", str(err))
    at, what, msg = _PARSE_AT.search(text), _PARSE_WHAT.search(text), _DEBUG_MSG.search(text)
    if at and what:
        text = f"{what.group(1)} at line {at.group(1)}, column {at.group(2)}"
    elif msg:
        text = msg.group(1)
    return " ".join(text.split()).rstrip(".") or type(err).__name__


@dataclass
class BusStats:
    """Counters a process reports in its status and summary."""

    published: Counter[str] = field(default_factory=Counter)
    received: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)
    callback_errors: Counter[str] = field(default_factory=Counter)
    oversized: Counter[str] = field(default_factory=Counter)   # sent over max_message_size
    last_error: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {
            "published": dict(self.published), "received": dict(self.received),
            "rejected": dict(self.rejected), "callback_errors": dict(self.callback_errors),
            "oversized": dict(self.oversized), "last_error": self.last_error,
        }


#: how often a client tries to reach its router again after losing it
RECONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 1.5}
#: Zenoh's shared-memory transport, off in every session we open (issue 42). With it on, a
#: client on the server's host puts payloads over ~3 kB into a 16 MiB pool of its own, and the
#: router maps and mlocks that pool plus a 1.25 MiB metadata segment and never unmaps them,
#: also after the client has gone (Zenoh 1.10; eclipse-zenoh/zenoh#2787): ~19.7 MB of server
#: memory per reconnecting client. We never allocate shared memory ourselves, so off costs us
#: only a loopback copy. Off also makes the link's max_message_size hold for every payload:
#: one in shared memory crosses the link as a small descriptor, past that check.
#: ``bench/zenoh_session_memory.py`` measures it.
SHARED_MEMORY = False


def zenoh_config(mode: Mode, listen: Iterable[str] = (), connect: Iterable[str] = (),
                 config_file: str | None = None, multicast_scouting: bool = False,
                 connect_timeout_ms: int | None = None,
                 max_message_size: int = DEFAULT_MAX_MESSAGE_SIZE) -> Any:
    """A ``zenoh.Config``: optional json5 file (TLS, access control) plus our settings.

    Raises ``BusError`` naming the file or the setting Zenoh refused.
    """
    import zenoh

    try:
        conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    except zenoh.ZError as e:
        raise BusError(f"Zenoh config {config_file}: {zenoh_message(e)}") from None
    settings: list[tuple[str, object]] = [("mode", mode)]
    if listen:
        settings.append(("listen/endpoints", list(listen)))
    if connect:
        settings.append(("connect/endpoints", list(connect)))
        if conf.get_json("connect/retry") in ("null", None):
            # a robot whose server restarted is served again within ~1 s, not after Zenoh's
            # default back-off of up to 4 s (a config file's own setting is kept)
            settings.append(("connect/retry", RECONNECT_RETRY))
    if connect_timeout_ms is not None:
        settings.append(("connect/timeout_ms", connect_timeout_ms))
    settings += [("scouting/multicast/enabled", multicast_scouting),
                 ("transport/link/rx/max_message_size", max_message_size),
                 # a config file's own value is overridden too: a router that accepts
                 # shared memory keeps every local client's pool (SHARED_MEMORY)
                 ("transport/shared_memory/enabled", SHARED_MEMORY)]
    for key, value in settings:
        try:
            conf.insert_json5(key, json.dumps(value))
        except zenoh.ZError as e:
            raise BusError(f"Zenoh setting {key} = {json.dumps(value)}: "
                           f"{zenoh_message(e)}") from None
    return conf


# -- who can reach a listening session --------------------------------------------------------
_LOCAL_PROTOCOLS = {"unixsock-stream", "unixpipe", "serial"}   # no network reaches these
_SECURE_PROTOCOLS = {"tls", "quic"}


def is_loopback_endpoint(endpoint: str) -> bool:
    """True when only this machine can reach ``endpoint`` (``tcp/127.0.0.1:7447``, a unix
    socket); False for any other address, a wildcard (``0.0.0.0``, ``[::]``) or a host name
    other than ``localhost``."""
    proto, _, address = endpoint.partition("/")
    if proto in _LOCAL_PROTOCOLS:
        return True
    address = address.split("?", 1)[0].split("#", 1)[0]
    host = address.rsplit(":", 1)[0] if ":" in address else address
    host = host.strip("[]").split("%", 1)[0]
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class ListenSecurity:
    """Where a session listens and what it lacks to be safe on a network.

    ``exposed`` are the endpoints other machines can reach; ``missing`` names what is absent
    for those (TLS with client certificates, access control). Both empty: loopback only.
    """

    endpoints: list[str]
    exposed: list[str]
    missing: list[str]

    @property
    def secure(self) -> bool:
        return not self.missing


def _json(conf: Any, key: str) -> Any:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # a key this Zenoh does not know reads as unset
        return None


def listen_security(conf: Any) -> ListenSecurity:
    """What the ``zenoh.Config`` ``conf`` would listen on, and whether that is secured.

    Clients do not listen. Without endpoints of its own a router or peer listens where Zenoh's
    defaults say (all interfaces). Endpoints off this machine need TLS (``tls/`` or ``quic/``
    with a CA and ``enable_mtls``, so that only holders of a signed certificate connect) and
    access control (``access_control.enabled``).
    """
    mode = _json(conf, "mode") or "peer"
    if mode == "client":
        return ListenSecurity([], [], [])
    endpoints = _json(conf, "listen/endpoints") or []
    if isinstance(endpoints, dict):   # per-mode defaults
        endpoints = endpoints.get(mode) or []
    endpoints = [str(e) for e in endpoints]
    exposed = [e for e in endpoints if not is_loopback_endpoint(e)]
    if not exposed:
        return ListenSecurity(endpoints, [], [])
    missing: list[str] = []
    plain = [e for e in exposed if e.partition("/")[0] not in _SECURE_PROTOCOLS]
    if plain:
        missing.append(f"TLS (not on {', '.join(plain)})")
    tls = _json(conf, "transport/link/tls") or {}
    if len(plain) < len(exposed):
        if not tls.get("root_ca_certificate"):
            missing.append("a CA (transport.link.tls.root_ca_certificate)")
        if tls.get("enable_mtls") is not True:
            missing.append("client certificates (transport.link.tls.enable_mtls)")
    if _json(conf, "access_control/enabled") is not True:
        missing.append("access control (access_control.enabled)")
    return ListenSecurity(endpoints, exposed, missing)


def insecure_listen_warning(sec: ListenSecurity) -> str:
    return (f"listening on {', '.join(sec.exposed)} without {' and '.join(sec.missing)} "
            "(bus.insecure_listen): anyone who reaches this host can read everything and send "
            "the robots commands; see deploy/README.md for TLS and access rules")


class Bus:
    """One Zenoh session with typed publish/subscribe, liveliness and queryables."""

    def __init__(self, session: Any, max_message_size: int = DEFAULT_MAX_MESSAGE_SIZE) -> None:
        self.session = session
        self.max_message_size = max_message_size
        self.stats = BusStats()
        self._publishers: dict[str, Any] = {}
        self._sent = itertools.count()
        self._handles: list[Any] = []
        self._lock = threading.Lock()
        self._closed = False
        self._zid: str | None = None
        #: where the session listens and what it connects to, as Zenoh was configured
        self.listening: list[str] = []
        self.connecting: list[str] = []

    @classmethod
    def open(cls, mode: Mode, listen: Iterable[str] = (), connect: Iterable[str] = (),
             config_file: str | None = None, connect_timeout_ms: int | None = None,
             max_message_size: int = DEFAULT_MAX_MESSAGE_SIZE) -> Bus:
        """Open a session. A router or peer listening beyond this machine without TLS and
        access control logs a warning every time (the config loader refuses that unless
        ``bus.insecure_listen`` is set)."""
        import zenoh

        zenoh.init_log_from_env_or("error")
        listen, connect = list(listen), list(connect)
        conf = zenoh_config(mode, listen, connect, config_file,
                            connect_timeout_ms=connect_timeout_ms,
                            max_message_size=max_message_size)
        # checked where the session opens, not where a config is validated (that may be on
        # another machine than the one it is for): Zenoh would only say "Timeout!"
        if problems := tls_file_problems(conf):
            raise BusError(f"Zenoh config {config_file}: {'; '.join(problems)}")
        sec = listen_security(conf)
        if not sec.secure:
            log.warning(insecure_listen_warning(sec))
        try:
            bus = cls(zenoh.open(conf), max_message_size)
        except zenoh.ZError as e:
            where = ", ".join(listen + connect) or ", ".join(sec.endpoints) or \
                "default endpoints"
            raise BusError(f"cannot open a Zenoh {mode} session on {where}: "
                           f"{zenoh_message(e)}") from None
        bus.listening = sec.endpoints
        bus.connecting = connect or [str(e) for e in _json(conf, "connect/endpoints") or []]
        return bus

    @classmethod
    def from_config(cls, cfg: BusConfig) -> Bus:
        """Open the session a process's ``bus`` config describes."""
        return cls.open(cfg.mode, cfg.listen, cfg.connect, cfg.zenoh_config,
                        cfg.connect_timeout_ms, cfg.max_message_size)

    @property
    def zid(self) -> str:
        """This session's Zenoh id (what receivers see as the source of its messages)."""
        if self._zid is None:
            self._zid = str(self.session.zid())
        return self._zid

    # -- publishing -------------------------------------------------------------------------
    def publish(self, key: str, msg: Message, *, block: bool = False) -> None:
        """Send ``msg`` on ``key``. When the link is congested, drop (default) or wait.

        The message carries this session's id as its source (``Sample.source_info``), which
        receivers may compare with the session they expect it from. Zenoh does not
        authenticate it: without TLS and access rules a sender can claim any source.
        """
        import zenoh

        pub = self._publishers.get(key)
        if pub is None:
            cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
            with self._lock:
                pub = self._publishers.get(key)
                if pub is None:
                    pub = self.session.declare_publisher(key, congestion_control=cc)
                    self._publishers[key] = pub
        payload = encode(msg)
        name = type(msg).__name__
        if len(payload) > self.max_message_size:
            self.stats.oversized[name] += 1
            n = self.stats.oversized[name]
            if n <= 3 or n % 1000 == 0:
                log.warning("%s #%d on %s is %d bytes, over bus.max_message_size (%d): "
                            "receivers with that limit drop it", name, n, key, len(payload),
                            self.max_message_size)
        pub.put(payload, source_info=zenoh.SourceInfo(pub.id, next(self._sent)))
        self.stats.published[name] += 1

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
        return self.subscribe_with_source(key, cls, lambda k, msg, _src: callback(k, msg))

    def subscribe_with_source(self, key: str, cls: type[M],
                              callback: Callable[[str, M, str | None], None]) -> Any:
        """Like ``subscribe``, with the id of the session the message says it came from
        (``None`` when the sender did not say: not a ``Bus.publish``)."""
        def with_source(k: str, msg: M, sample: Any) -> None:
            info = sample.source_info
            callback(k, msg, None if info is None else str(info.source_id.zid))

        return self._subscribe(key, cls, with_source)

    def subscribe_received(self, key: str, cls: type[M],
                           callback: Callable[[str, M, int], None]) -> Any:
        """Like ``subscribe``, with the time the message reached this process [ns since the
        epoch, this machine's clock] (``received_ns``)."""
        return self._subscribe(key, cls,
                               lambda k, msg, sample: callback(k, msg, self.received_ns(sample)))

    def subscribe_polled(self, key: str, cls: type[M], keep: int = 256) -> Polled[M]:
        """Samples of ``cls`` on ``key`` kept by Zenoh (the latest ``keep``) until ``drain``
        takes them: unlike a callback's, they are there as soon as their bytes arrive, so a
        thread that drains before it judges another message knows every one that came
        first (the simulator's clock, before a scan that must be placed in its time)."""
        import zenoh

        sub = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(keep))
        self._handles.append(sub)
        return Polled(self, sub, cls)

    def received_ns(self, sample: Any) -> int:
        """When ``sample``'s bytes reached this session. A router stamps every sample as it
        arrives, in Zenoh's own threads, so a stall of ours (the GIL held by a long
        computation) does not make it later; a sample stamped elsewhere (by its sender, or by
        another router with its own clock), or not at all, gets the time its callback ran,
        which is never earlier than its arrival."""
        now = time.time_ns()
        ts = sample.timestamp
        if ts is None or str(ts.get_id()) != self.zid:
            return now
        return min(now, ts.get_time_as_ntp64().as_nanos())

    def _subscribe(self, key: str, cls: type[M],
                   callback: Callable[[str, M, Any], None]) -> Any:
        name = cls.__name__

        def on_sample(sample: Any) -> None:
            k = str(sample.key_expr)
            if self._oversized(name, k, sample):
                return
            try:
                msg = decode(sample.payload.to_bytes(), cls)
            except SchemaError as e:
                self._reject(name, k, e)
                return
            self.stats.received[name] += 1
            try:
                callback(k, msg, sample)
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
            if self._oversized("raw", str(sample.key_expr), sample):
                return
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:
                self.stats.callback_errors["raw"] += 1
                log.exception("raw handler for %s failed", sample.key_expr)

        sub = self.session.declare_subscriber(key, on_sample)
        self._handles.append(sub)
        return sub

    def watch_senders(self, key: str, callback: Callable[[str, str | None], None]) -> Any:
        """Call ``callback(key, sender)`` for every sample on ``key`` that another session
        sent (``sender``: its id, None when it did not say), without decoding it: who else
        publishes where only this session should."""
        mine = self.zid

        def on_sample(sample: Any) -> None:
            info = sample.source_info
            sender = None if info is None else str(info.source_id.zid)
            if sender == mine:
                return
            try:
                callback(str(sample.key_expr), sender)
            except Exception:
                self.stats.callback_errors["senders"] += 1
                log.exception("sender handler for %s failed", sample.key_expr)

        sub = self.session.declare_subscriber(key, on_sample)
        self._handles.append(sub)
        return sub

    def _oversized(self, name: str, key: str, sample: Any) -> bool:
        """True (counted as rejected, logged) when the payload is over ``max_message_size``."""
        size = len(sample.payload)
        if size <= self.max_message_size:
            return False
        self._reject(name, key, f"{size} bytes, over bus.max_message_size "
                                f"({self.max_message_size})")
        return True

    def _reject(self, name: str, key: str, err: SchemaError | str) -> None:
        self.stats.rejected[name] += 1
        self.stats.last_error = f"{key}: {err}"
        n = self.stats.rejected[name]
        if n <= 10 or n % 1000 == 0:  # logged, but a flood of garbage cannot flood the log
            log.warning("rejected message #%d on %s: %s", n, key, err)

    # -- liveliness -------------------------------------------------------------------------
    def declare_alive(self, key: str) -> Any:
        """Declare the liveliness token ``key``, and beside it ``<key>/zid/<this session>``:
        Zenoh's liveliness samples do not say whose token they are, and a receiver that must
        tell the server's messages from others' learns the server's session from it
        (``watch_holders``). The companion comes first, so it is known when ``key`` is."""
        holder = self.session.liveliness().declare_token(f"{key}/{HOLDER_CHUNK}/{self.zid}")
        self._handles.append(holder)
        token = self.session.liveliness().declare_token(key)
        self._handles.append(token)
        return token

    def declare_token(self, key: str) -> Any:
        """A bare liveliness token on ``key`` (no holder companion); ``undeclare`` ends it."""
        token = self.session.liveliness().declare_token(key)
        with self._lock:
            self._handles.append(token)
        return token

    def undeclare(self, handle: Any) -> None:
        """End a token, subscription or queryable this bus declared."""
        with self._lock:
            if handle in self._handles:
                self._handles.remove(handle)
        with contextlib.suppress(Exception):   # already gone with the session
            handle.undeclare()

    def watch_holders(self, key: str, callback: Callable[[str, bool], None]) -> Any:
        """Call ``callback(zid, alive)`` when a session declaring ``key`` with
        ``declare_alive`` appears or goes (existing ones on declaration)."""
        prefix = f"{key}/{HOLDER_CHUNK}/"

        def on_holder(token_key: str, alive: bool) -> None:
            if token_key.startswith(prefix):
                callback(token_key[len(prefix):], alive)

        return self.watch_alive(f"{prefix}*", on_holder)

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

    def serve_queries(self, key: str, on_query: Callable[[Any], None]) -> Any:
        """Hand each query on ``key`` to ``on_query`` (on a Zenoh thread). The query may be
        answered later, from any thread: ``query.reply(key, bytes)`` as often as needed,
        or ``query.reply_err(bytes)``, then ``query.drop()`` ends it."""

        def guarded(query: Any) -> None:
            try:
                on_query(query)
            except Exception as e:
                log.exception("queryable %s failed", key)
                query.reply_err(f"{type(e).__name__}: {e}".encode())
                query.drop()

        q = self.session.declare_queryable(key, guarded)
        self._handles.append(q)
        return q

    def ask(self, key: str, payload: bytes,
            on_done: Callable[[list[bytes], list[str]], None], timeout_s: float) -> None:
        """Query ``key`` with ``payload`` without waiting: every reply is kept (none merged
        away), and ``on_done(replies, errors)`` is called once, on a Zenoh thread, when the
        query has ended (all answered, or ``timeout_s`` passed)."""
        import zenoh

        replies: list[bytes] = []
        errors: list[str] = []

        def on_reply(reply: Any) -> None:
            if reply.ok is not None:
                replies.append(reply.ok.payload.to_bytes())
            else:
                errors.append(reply.err.payload.to_bytes().decode(errors="replace"))

        def on_end() -> None:
            try:
                on_done(replies, errors)
            except Exception:
                log.exception("the answer to %s could not be taken", key)

        self.session.get(key, zenoh.handlers.Callback(on_reply, on_end), payload=payload,
                         consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)

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


class Polled(Generic[M]):
    """A subscription drained on demand (``Bus.subscribe_polled``); any thread."""

    def __init__(self, bus: Bus, sub: Any, cls: type[M]) -> None:
        self._bus, self._sub, self._cls = bus, sub, cls
        self._lock = threading.Lock()

    def drain(self) -> list[tuple[M, int]]:
        """Every valid message that came since the last drain, with its receipt [ns]."""
        name = self._cls.__name__
        out: list[tuple[M, int]] = []
        with self._lock:
            while True:
                sample = self._sub.try_recv()
                if sample is None:
                    return out
                k = str(sample.key_expr)
                if self._bus._oversized(name, k, sample):
                    continue
                try:
                    msg = decode(sample.payload.to_bytes(), self._cls)
                except SchemaError as e:
                    self._bus._reject(name, k, e)
                    continue
                self._bus.stats.received[name] += 1
                out.append((msg, self._bus.received_ns(sample)))
