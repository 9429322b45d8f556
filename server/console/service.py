"""The operator console: a web page served by the server itself (``mrslam server --console
PORT``), live from the server's own outputs, with fleet controls that go through the server.

How it keeps off the server's back:

1. It listens to the server's messages on the bus like any client would (maps, robot states,
   events); each arrives in a callback that only appends to a bounded inbox (the oldest
   dropped first) — the server's worker never waits for the console. The robots' health
   comes from the node's own counters, read once a second.
2. Its own thread decodes the inbox, keeps the page's model (``server.console.model``),
   encodes each frame once and puts it in every open page's bounded queue
   (``server.console.clients``).
3. Each page has its own HTTP thread that sends what its queue holds; a page that stops
   reading is dropped after a few seconds.

Orders (``/command``) are parsed here and handed to the node (``ServerNode.operate``), which
journals them and has the core carry them out; the answer says what was done or why not.
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from importlib import resources
from typing import Any

from schemas import Event, MapUpdate, RobotStates, keys
from schemas.bus import Bus
from schemas.codec import decode
from schemas.errors import SchemaError
from schemas.ratelog import RateLimitedLog
from server.command.operator import OperatorCommand, OperatorError, parse
from server.console.clients import Pages, encode
from server.console.model import ConsoleModel, Frame
from server.console.web import ConsoleHTTPServer

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
#: the environment variable that sets the token (else a new one is made at each start)
TOKEN_ENV = "MRSLAM_CONSOLE_TOKEN"
#: messages waiting for the console's thread before the oldest go
INBOX = 2000
#: pages open at once
MAX_PAGES = 16
#: how long a command's asker waits for the server's answer [s]
ANSWER_TIMEOUT_S = 3.0


class ConsoleError(RuntimeError):
    """The console could not start (port taken, bad address, bad token)."""

    user_error = True


def new_token() -> str:
    return secrets.token_urlsafe(18)


class Console:
    """The console of one server: its model, its pages, its HTTP server."""

    def __init__(self, port: int, operate: Callable[[OperatorCommand], Future[Any]],
                 health: Callable[[], dict[str, Any]],
                 token: str | None = None, host: str = DEFAULT_HOST) -> None:
        """``operate``: hands an order to the server (``ServerNode.operate``); ``health``:
        the node's scans accepted and dropped per robot and its orders' view
        (``ServerNode.health``; any thread)."""
        self.token = token or new_token()
        if len(self.token) < 16:
            raise ConsoleError("the console's token must be at least 16 characters")
        self.operate, self.health = operate, health
        self.model = ConsoleModel()
        self.pages = Pages(MAX_PAGES)
        self.counters: Counter[str] = Counter()
        #: CPU time the console took in the server's process [s]: its thread, its pages'
        #: threads and its bus callbacks
        self.cpu_s = 0.0
        self._cpu_lock = threading.Lock()
        self.closing = False
        self._lock = threading.Lock()          # the model: the console's thread and new pages
        self._inbox: deque[tuple[str, bytes, float]] = deque(maxlen=INBOX)
        self._wake = threading.Event()
        self.errlog = RateLimitedLog(log)
        self._page = resources.files("server.console").joinpath("page.html").read_bytes()
        try:
            self.http = ConsoleHTTPServer((host, port), self)
        except OSError as e:
            raise ConsoleError(f"console on {host}:{port}: {e.strerror or e}") from e
        self.host = host
        self._threads = [
            threading.Thread(target=self.http.serve_forever, kwargs={"poll_interval": 0.2},
                             name="console-http", daemon=True),
            threading.Thread(target=self._run, name="console", daemon=True)]
        for t in self._threads:
            t.start()
        log.info("console on %s", self.url)

    @property
    def port(self) -> int:
        return int(self.http.server_address[1])

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/?token={self.token}"

    def attach(self, bus: Bus) -> None:
        """Listen to the server's outputs (and the robots' scans) on ``bus``."""
        for key in (keys.SERVER_MAP, keys.SERVER_ROBOTS, keys.SERVER_EVENTS):
            bus.subscribe_raw(key, self._arrived)

    def add_cpu(self, since_thread_s: float) -> None:
        """Count this thread's CPU time since ``since_thread_s`` (``time.thread_time()``)."""
        used = time.thread_time() - since_thread_s
        with self._cpu_lock:
            self.cpu_s += used

    # -- the bus's threads (and the server's worker, for its own messages): append only ------
    def _arrived(self, key: str, payload: bytes) -> None:
        t0 = time.thread_time()
        if len(self._inbox) == INBOX:
            self.counters["inbox_dropped"] += 1
        self._inbox.append((key, payload, time.time()))
        self._wake.set()
        self.add_cpu(t0)

    # -- the console's thread --------------------------------------------------------------
    def _run(self) -> None:
        next_health = 0.0
        while not self.closing:
            self._wake.wait(0.25)
            self._wake.clear()
            t0 = time.thread_time()
            while self._inbox:
                key, payload, seen = self._inbox.popleft()
                try:
                    frame = self._ingest(key, payload, seen)
                except (SchemaError, ValueError) as e:
                    self.counters["undecodable"] += 1
                    self.errlog.warning(type(e).__name__, "console: %s did not decode: %s",
                                        key, e)
                    continue
                except Exception as e:   # the console must never take the server down
                    self.counters["errors"] += 1
                    self.errlog.log(logging.ERROR, type(e).__name__,
                                    "console: %s failed", key, exc_info=True)
                    continue
                if frame is not None:
                    self.pages.send(frame)
            now = time.monotonic()
            if now >= next_health:
                next_health = now + 1.0
                try:
                    health = self.health()
                    with self._lock:
                        self.model.on_counts(health["scans"], time.time())
                    self.pages.send(self._health(health))
                except Exception:
                    self.counters["errors"] += 1
                    self.errlog.log(logging.ERROR, "health", "console: health failed",
                                    exc_info=True)
            self.add_cpu(t0)

    def _ingest(self, key: str, payload: bytes, seen: float) -> Frame | None:
        with self._lock:
            if key == keys.SERVER_MAP:
                return self.model.on_map(decode(payload, MapUpdate), seen)
            if key == keys.SERVER_ROBOTS:
                return self.model.on_robots(decode(payload, RobotStates), seen)
            if key == keys.SERVER_EVENTS:
                return self.model.on_event(decode(payload, Event))
        return None

    def _health(self, health: dict[str, Any] | None = None) -> Frame:
        health = health if health is not None else self.health()
        counters = {**self.counters, **self.pages.counters(), "cpu_s": round(self.cpu_s, 3)}
        with self._lock:
            return self.model.health_frame(health["dropped"], health["orders"], counters,
                                           state=health.get("state"))

    # -- what the pages ask (their HTTP threads) -------------------------------------------
    def page(self) -> bytes:
        return self._page

    def snapshot(self) -> Frame:
        health = self._health()
        with self._lock:
            return self.model.snapshot(health)

    def encoded_snapshot(self) -> bytes:
        health = self._health()
        with self._lock:        # encoded under the lock: the model's lists keep changing
            return encode(self.model.snapshot(health))

    def count(self, what: str) -> None:
        self.counters[what] += 1

    def command(self, body: bytes) -> tuple[int, dict[str, Any]]:
        """An order from a page: (HTTP status, answer). Malformed or refused orders are
        counted and logged, and answered with the reason."""
        try:
            try:
                data = json.loads(body)
            except (UnicodeDecodeError, json.JSONDecodeError) as e:
                raise OperatorError(f"body: not JSON ({e})") from e
            cmd = parse(data)
        except OperatorError as e:
            self.counters["bad_commands"] += 1
            self.errlog.warning("bad-command", "console: a command refused: %s", e)
            return e.status, {"ok": False, "error": str(e)}
        self.counters["commands"] += 1
        log.info("console: %s", cmd.describe())
        answer = self.operate(cmd)
        try:
            status, line = answer.result(timeout=ANSWER_TIMEOUT_S)
        except FutureTimeout:
            return 202, {"ok": None, "message": f"{cmd.describe()}: queued, not yet done"}
        except Exception as e:
            self.counters["errors"] += 1
            return 500, {"ok": False, "error": f"{type(e).__name__}: {e}"}
        if status != 200:
            self.counters["commands_refused"] += 1
            return status, {"ok": False, "error": line}
        return 200, {"ok": True, "message": line}

    def close(self) -> None:
        self.closing = True
        self._wake.set()
        self.pages.close_all()
        self.http.shutdown()
        self.http.server_close()
        for t in self._threads:
            t.join(timeout=5)

    def __enter__(self) -> Console:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
