"""The console's HTTP side: the page, its live stream, its controls — each behind the token.

| path | method | what |
|---|---|---|
| `/` | GET | the page (one self-contained HTML file) |
| `/stream` | GET | server-sent events: a `snapshot`, then `map`, `robots`, `event`, `health` |
| `/state` | GET | the snapshot as one JSON document |
| `/command` | POST | an operator's order (JSON, ``server.command.operator``) |

Every request carries the token: ``Authorization: Bearer <token>`` or ``?token=<token>``
(the page passes on the one in its own address). Without it, or with a wrong one, the answer
is 401 with an empty body: no page, no data, no control.
"""

from __future__ import annotations

import hmac
import json
import logging
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, urlsplit

if TYPE_CHECKING:
    from server.console.service import Console

log = logging.getLogger(__name__)

#: the largest command body taken [bytes]
MAX_BODY = 4096
#: a page that has not taken a frame for this long is dropped [s]
SEND_TIMEOUT_S = 5.0
#: a comment line keeps a quiet stream open (and finds pages that went away) [s]
KEEPALIVE_S = 10.0
#: connections served at once (each has a thread); more are closed at once
MAX_CONNECTIONS = 64

_HEADERS = {
    "Cache-Control": "no-store",
    "Referrer-Policy": "no-referrer",       # the token is in the page's address
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Content-Security-Policy": ("default-src 'none'; script-src 'unsafe-inline'; "
                                "style-src 'unsafe-inline'; connect-src 'self'; "
                                "img-src 'self' data:"),
}


class ConsoleHTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True   # a restarted server takes its port back at once

    def __init__(self, address: tuple[str, int], console: Console) -> None:
        self.console = console
        self._slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        super().__init__(address, ConsoleHandler)

    def process_request(self, request: Any, client_address: Any) -> None:
        """A thread per connection, up to ``MAX_CONNECTIONS``: a flood of connections
        cannot take the server's memory or threads."""
        if not self._slots.acquire(blocking=False):
            self.console.count("connections_refused")
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except Exception:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


class ConsoleHandler(BaseHTTPRequestHandler):
    server: ConsoleHTTPServer
    protocol_version = "HTTP/1.1"
    timeout = 15.0        # a connection that sends nothing for this long is closed
    server_version = "mrslam-console"
    sys_version = ""

    # -- plumbing ----------------------------------------------------------------------
    def handle_one_request(self) -> None:
        t0 = time.thread_time()
        self._cpu_from = t0
        try:
            super().handle_one_request()
        finally:
            self.server.console.add_cpu(self._cpu_from)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s %s", self.address_string(), format % args)

    def _authorised(self) -> bool:
        token = self.server.console.token.encode()
        given = ""
        auth = self.headers.get("Authorization", "")
        if auth.startswith("Bearer "):
            given = auth[len("Bearer "):].strip()
        else:
            given = parse_qs(urlsplit(self.path).query).get("token", [""])[0]
        if hmac.compare_digest(given.encode(), token):
            return True
        self.server.console.count("unauthorised")
        self.server.console.errlog.warning(
            "unauthorised", "console: a request without the right token (%s %s) from %s",
            self.command, urlsplit(self.path).path, self.client_address[0])
        self._send(HTTPStatus.UNAUTHORIZED, b"", "text/plain")
        return False

    def _send(self, status: HTTPStatus, body: bytes, ctype: str) -> None:
        self.send_response(status)
        for k, v in _HEADERS.items():
            self.send_header(k, v)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: HTTPStatus, data: dict[str, Any]) -> None:
        self._send(status, json.dumps(data).encode(), "application/json")

    # -- routes ------------------------------------------------------------------------
    def do_GET(self) -> None:
        if not self._authorised():
            return
        path = urlsplit(self.path).path
        console = self.server.console
        if path in ("/", "/index.html"):
            self._send(HTTPStatus.OK, console.page(), "text/html; charset=utf-8")
        elif path == "/state":
            self._json(HTTPStatus.OK, console.snapshot().data)
        elif path == "/stream":
            self._stream()
        else:
            console.count("bad_requests")
            self._json(HTTPStatus.NOT_FOUND, {"error": f"no such path {path}"})

    def do_POST(self) -> None:
        if not self._authorised():
            return
        console = self.server.console
        if urlsplit(self.path).path != "/command":
            console.count("bad_requests")
            self._json(HTTPStatus.NOT_FOUND, {"error": "commands go to /command"})
            return
        try:
            length = int(self.headers.get("Content-Length", ""))
        except ValueError:
            length = -1
        if not 0 < length <= MAX_BODY:
            console.count("bad_requests")
            self.close_connection = True
            self._json(HTTPStatus.BAD_REQUEST,
                       {"error": f"body: a JSON command of 1-{MAX_BODY} bytes with its "
                                 f"Content-Length"})
            return
        status, answer = console.command(self.rfile.read(length))
        self._json(HTTPStatus(status), answer)

    def do_PUT(self) -> None:
        self._refuse()

    def do_DELETE(self) -> None:
        self._refuse()

    def _refuse(self) -> None:
        if self._authorised():
            self.server.console.count("bad_requests")
            self._json(HTTPStatus.METHOD_NOT_ALLOWED, {"error": f"no {self.command} here"})

    def _stream(self) -> None:
        console = self.server.console
        pages = console.pages
        q = pages.open()
        if q is None:
            console.count("pages_refused")
            self._json(HTTPStatus.SERVICE_UNAVAILABLE,
                       {"error": f"{pages.limit} pages are open already"})
            return
        self.close_connection = True
        self.connection.settimeout(SEND_TIMEOUT_S)   # a page that stops reading is dropped
        try:
            self.send_response(HTTPStatus.OK)
            for k, v in _HEADERS.items():
                self.send_header(k, v)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(b"retry: 1000\n\n" + console.encoded_snapshot())
            self.wfile.flush()
            while not console.closing:
                console.add_cpu(self._cpu_from)     # counted as it goes: a stream lasts
                frames = q.take(KEEPALIVE_S)
                self._cpu_from = time.thread_time()
                if q.closed:
                    break
                self.wfile.write(b"".join(frames) if frames else b": keep-alive\n\n")
                self.wfile.flush()
        except OSError as e:      # a timeout too
            log.debug("console: a page went away (%s)", e)
        finally:
            pages.close(q)
