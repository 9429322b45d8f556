"""A server split over two hosts: each worker in a network namespace of its own, the router of
its host, linked to the robots' site router over a virtual cable (a veth pair). Robots are
served across the link; a worker stopped on purpose hands its teams over the link to the
other host, maps and all; a host whose cable is pulled has its robots taken over by the other
once its tokens have lapsed and the handover timeout has passed.

Needs root and ``ip netns`` (iproute2); skips, saying which, where either is missing."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.support.fleet import RoomRobot, ServerProcess
from schemas import keys
from schemas.bus import Bus, free_local_endpoint
from server.runtime.cluster import _rank
from tests.waiting import within

pytestmark = pytest.mark.e2e

MINE_1, MINE_0 = ("r1", "r2"), ("r7",)     # how rendezvous hashing ranks them over {0, 1}
LATER_1 = "r3"                              # ranks for worker 1 too


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=False)


class Hosts:
    """Two namespaces ``<tag>h0`` and ``<tag>h1``, each with its loopback up and a veth pair
    to this namespace: 10.<net>.<h+1>.1 here, .2 there."""

    def __init__(self) -> None:
        tag = uuid.uuid4().hex[:4]
        self.names = [f"ms{tag}h{h}" for h in (0, 1)]
        self.cables = [f"ms{tag}c{h}" for h in (0, 1)]
        self.net = 100 + int(tag, 16) % 100
        for h, (ns, cable) in enumerate(zip(self.names, self.cables, strict=True)):
            for args in (("netns", "add", ns),
                         ("link", "add", cable, "type", "veth", "peer", "name", f"{cable}p"),
                         ("link", "set", f"{cable}p", "netns", ns),
                         ("addr", "add", f"{self.here(h)}/24", "dev", cable),
                         ("link", "set", cable, "up"),
                         ("-n", ns, "addr", "add", f"{self.there(h)}/24", "dev", f"{cable}p"),
                         ("-n", ns, "link", "set", f"{cable}p", "up"),
                         ("-n", ns, "link", "set", "lo", "up")):
                r = _ip(*args)
                if r.returncode != 0:
                    self.close()
                    raise OSError(f"ip {' '.join(args)}: {r.stderr.strip()}")

    def here(self, h: int) -> str:
        return f"10.{self.net}.{h + 1}.1"

    def there(self, h: int) -> str:
        return f"10.{self.net}.{h + 1}.2"

    def prefix(self, h: int) -> tuple[str, ...]:
        return ("ip", "netns", "exec", self.names[h])

    def cut(self, h: int) -> None:
        r = _ip("link", "set", self.cables[h], "down")
        assert r.returncode == 0, r.stderr

    def close(self) -> None:
        for ns, cable in zip(self.names, self.cables, strict=True):
            _ip("link", "del", cable)
            _ip("netns", "del", ns)


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) to make network namespaces")
    try:
        h = Hosts()
    except OSError as e:
        pytest.skip(f"cannot make network namespaces here: {e}")
    try:
        yield h
    finally:
        h.close()


def test_two_hosts_serve_hand_over_and_take_over_a_cut_host(hosts: Hosts,
                                                            tmp_path: Path) -> None:
    assert all(max((0, 1), key=lambda w: _rank(r, w)) == 1 for r in (*MINE_1, LATER_1))
    assert all(max((0, 1), key=lambda w: _rank(r, w)) == 0 for r in MINE_0)
    port = free_local_endpoint().rsplit(":", 1)[1]
    site = [f"tcp/127.0.0.1:{port}", *(f"tcp/{hosts.here(h)}:{port}" for h in (0, 1))]

    def worker(h: int, folder: str) -> ServerProcess:
        (tmp_path / folder).mkdir()
        # each worker is its host's router (robots on that host would connect to it), and
        # reaches the site over its cable
        cfg = {"cluster": {"worker": h, "handover_timeout_s": 3.0},
               "bus": {"mode": "router", "listen": [f"tcp/127.0.0.1:{port}"],
                       "connect": [f"tcp/{hosts.here(h)}:{port}"]}}
        return ServerProcess(tmp_path / folder, cfg, prefix=hosts.prefix(h))

    owners: dict[str, set[int]] = {}
    workers_seen: set[str] = set()
    lock = threading.Lock()

    def on_owner(key: str, alive: bool) -> None:
        parsed = keys.cluster_owner_of(key)
        if parsed is not None:
            with lock:
                (owners.setdefault(parsed[0], set()).add if alive else
                 owners.setdefault(parsed[0], set()).discard)(parsed[1])

    def served_by(w: int, rids: tuple[str, ...]) -> bool:
        with lock:
            return all(owners.get(r) == {w} for r in rids)

    def on_worker(key: str, alive: bool) -> None:
        with lock:
            (workers_seen.add if alive else workers_seen.discard)(key)

    robots: list[RoomRobot] = []
    procs: list[ServerProcess] = []
    with Bus.open("router", listen=site) as _site, \
            Bus.open("client", connect=[site[0]]) as watch:
        try:
            watch.watch_alive(keys.ALL_CLUSTER_OWNERS, on_owner)
            watch.watch_alive(keys.ALL_CLUSTER_WORKERS, on_worker)
            w0, w1 = worker(0, "w0"), worker(1, "w1")
            procs += [w0, w1]
            assert within(lambda: len(workers_seen) == 2, 60.0), (
                w0.log_lines()[-5:], w1.log_lines()[-5:])
            time.sleep(1.0)
            # robots at the site, each served by the worker it ranks for, across its cable
            robots += [RoomRobot(site[0], r).start() for r in (*MINE_1, *MINE_0)]
            assert within(lambda: served_by(1, MINE_1) and served_by(0, MINE_0), 30.0)
            assert within(lambda: all(r.answered_since(time.monotonic() - 1.0) >= 5
                                      for r in robots), 30.0)
            time.sleep(2.0)
            # host 1's worker stopped on purpose: its teams cross to host 0, maps and all
            assert w1.stop() == 0
            assert within(lambda: served_by(0, MINE_1 + MINE_0), 15.0)
            given = json.loads((tmp_path / "w1" / "server" / "summary.json").read_text())
            assert given["cluster"]["given"] == len(MINE_1)
            assert within(lambda: robots[0].answered_since(time.monotonic() - 1.0) >= 5, 30.0)
            # a new worker on host 1 serves a new robot; then host 1's cable is pulled
            assert within(lambda: len(workers_seen) == 1, 15.0)
            w1 = worker(1, "w1b")
            procs.append(w1)
            assert within(lambda: len(workers_seen) == 2, 60.0)
            time.sleep(1.0)
            robots.append(RoomRobot(site[0], LATER_1).start())
            assert within(lambda: served_by(1, (LATER_1,)), 30.0)
            hosts.cut(1)
            t_cut = time.monotonic()
            # its tokens lapse with the link's lease, then host 0 serves the robot (afresh)
            assert within(lambda: served_by(0, (LATER_1,)), 40.0)
            assert time.monotonic() - t_cut >= 3.0
            assert within(lambda: robots[-1].answered_since(time.monotonic() - 1.0) >= 5,
                          30.0)
            assert w1.proc.poll() is None        # the cut-off worker itself lives on
            assert w0.stop() == 0
            summary = json.loads((tmp_path / "w0" / "server" / "summary.json").read_text())
            assert summary["cluster"]["adopted"] == len(MINE_1)
            assert set(summary["cluster"]["robots_served"]) == {*MINE_1, *MINE_0, LATER_1}
            # the team that crossed kept its map: its scans from host 1 went on in host 0
            assert summary["robots"]["r1"]["scans"] > 50
        finally:
            for r in robots:
                r.close()
            for p in procs:
                p.stop()
