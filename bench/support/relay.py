"""A TCP relay between a robot and the server: a link that can be slow, bursty or cut.

This machine's kernel has no ``netem``, so the tests and benches that need a bad network put
this in the path instead: the agent connects to the relay, the relay to the server's router.
Bytes from the robot go through a delay line: each chunk is held until its release time (now
plus a random jitter, or the end of a burst in progress), and chunks never overtake each other,
as on a TCP connection. ``hold(s)`` is a Wi-Fi stall while the robot roams between access
points: nothing gets through for ``s`` seconds, then everything held arrives at once.
``cut(s)`` closes the connections and refuses new ones for ``s`` seconds. Bytes from the server
to the robot pass straight through.
"""

from __future__ import annotations

import contextlib
import random
import socket
import threading
import time
from collections import deque


class Relay:
    def __init__(self, upstream: str, jitter_s: float = 0.0, seed: int = 0) -> None:
        """``upstream``: the router's endpoint, ``tcp/HOST:PORT``; ``jitter_s``: each chunk
        from the robot is delayed by a uniform random time up to this."""
        host, port = upstream.removeprefix("tcp/").rsplit(":", 1)
        self.upstream = (host, int(port))
        self.jitter_s = jitter_s
        self._rng = random.Random(seed)
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = f"tcp/127.0.0.1:{self._listener.getsockname()[1]}"
        self._hold_until = 0.0
        self._cut_until = 0.0
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self._closed = threading.Event()
        self.held_chunks = 0        # chunks that waited for a burst to end
        threading.Thread(target=self._accept, daemon=True, name="relay-accept").start()

    # -- what the link does ------------------------------------------------------------------
    def hold(self, seconds: float) -> None:
        """From now, nothing from the robot gets through for ``seconds``; then all of it."""
        with self._lock:
            self._hold_until = time.monotonic() + seconds

    def cut(self, seconds: float) -> None:
        """Close every connection now and refuse new ones for ``seconds``."""
        with self._lock:
            self._cut_until = time.monotonic() + seconds
            conns, self._conns = self._conns, []
        for s in conns:
            _close(s)

    def close(self) -> None:
        self._closed.set()
        _close(self._listener)
        self.cut(0.0)

    def __enter__(self) -> Relay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- plumbing ----------------------------------------------------------------------------
    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                robot, _ = self._listener.accept()
            except OSError:
                return
            if time.monotonic() < self._cut_until:
                _close(robot)
                continue
            try:
                server = socket.create_connection(self.upstream, timeout=5.0)
            except OSError:
                _close(robot)
                continue
            server.settimeout(None)
            for s in (robot, server):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._conns += [robot, server]
            line: deque[tuple[float, bytes]] = deque()
            ready = threading.Condition()
            threading.Thread(target=self._take, args=(robot, server, line, ready),
                             daemon=True).start()
            threading.Thread(target=self._release, args=(server, robot, line, ready),
                             daemon=True).start()
            threading.Thread(target=_pump, args=(server, robot), daemon=True).start()

    def _take(self, robot: socket.socket, server: socket.socket,
              line: deque[tuple[float, bytes]], ready: threading.Condition) -> None:
        """Robot → delay line: each chunk with the time it may go on."""
        last = 0.0
        while True:
            try:
                data = robot.recv(65536)
            except OSError:
                data = b""
            now = time.monotonic()
            with self._lock:
                hold_until = self._hold_until
            at = max(now + self._rng.uniform(0.0, self.jitter_s), last)
            if hold_until > now:
                at = max(at, hold_until)
                self.held_chunks += 1
            last = at
            with ready:
                line.append((at, data))
                ready.notify()
            if not data:
                return

    def _release(self, server: socket.socket, robot: socket.socket,
                 line: deque[tuple[float, bytes]], ready: threading.Condition) -> None:
        """Delay line → server, each chunk at its time, in order."""
        while True:
            with ready:
                ready.wait_for(lambda: bool(line))
                at, data = line[0]
            wait = at - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            with ready:
                line.popleft()
            if not data:
                break
            try:
                server.sendall(data)
            except OSError:
                break
        _close(server)
        _close(robot)


def _pump(src: socket.socket, dst: socket.socket) -> None:
    while True:
        try:
            data = src.recv(65536)
            if not data:
                break
            dst.sendall(data)
        except OSError:
            break
    _close(src)
    _close(dst)


def _close(s: socket.socket) -> None:
    with contextlib.suppress(OSError):
        s.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(OSError):
        s.close()
