"""Issue 42, finding 2: a client session that sent large payloads must leave nothing behind
in the server's router. With Zenoh's shared memory on, the router mapped and locked each local
client's 16 MiB pool for good (~19.7 MB per session); every session we open turns it off."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from schemas.bus import DEFAULT_MAX_MESSAGE_SIZE, Bus, zenoh_config
from tests.waiting import within

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "bench" / "zenoh_session_memory.py"


def test_no_session_we_open_offers_shared_memory(tmp_path: Path) -> None:
    own = tmp_path / "zenoh.json5"
    own.write_text("{ transport: { shared_memory: { enabled: true } } }")
    for conf in (zenoh_config("router", ["tcp/127.0.0.1:7447"]),
                 zenoh_config("client", connect=["tcp/127.0.0.1:7447"]),
                 zenoh_config("peer"),
                 zenoh_config("router", config_file=str(own))):
        assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False


@pytest.mark.e2e
def test_thirty_client_sessions_of_large_payloads_leave_the_router_flat() -> None:
    """The server's router config (the bench's ``mrslam`` variant) against plain Zenoh
    clients with their default config (shared memory on), each in its own process, 2 x 2 MB
    each. Before the fix this grew by ~10-20 MB per session (300-600 MB here)."""
    out = subprocess.run([sys.executable, str(BENCH), "--variant", "mrslam", "--sessions", "30",
                          "--messages", "2", "--size", "2000000", "--settle", "0.5"],
                         capture_output=True, text=True, timeout=120, cwd=ROOT, check=True)
    run = json.loads(out.stdout)["runs"][0]
    assert run["variant"] == "mrslam"
    assert run["growth_mb"] < 40, run
    assert run["zenoh_shm_mappings_after"] == 0, run
    assert run["after_mb"]["RssShmem"] - run["before_mb"]["RssShmem"] < 1.0, run


_SENDER = """
import json, os, sys, time, zenoh
conf = zenoh.Config()   # Zenoh's defaults: shared memory on
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(conf)
block = zenoh.CongestionControl.BLOCK
s.put("junk/big", os.urandom(2_000_000), congestion_control=block)
time.sleep(0.5)   # a shared-memory pool would be ready by now: later ones would use it
for key, size in (("junk/big", 2_000_000), ("junk/small", 100), ("junk/big", 2_000_000),
                  ("junk/frame", 307_200), ("junk/end", 100)):
    s.put(key, os.urandom(size), congestion_control=block)
time.sleep(0.3)
s.close()
"""


@pytest.mark.e2e
def test_the_link_cap_holds_for_every_large_payload_of_a_local_client(
        router: Bus, endpoint: str) -> None:
    """Shared memory carried a local client's payloads as small descriptors, past the link's
    max_message_size: only the first oversized one was dropped there. Now Zenoh's link drops
    each of them, and a camera frame still arrives."""
    got: list[tuple[str, int]] = []
    router.subscribe_raw("junk/**", lambda k, b: got.append((k, len(b))))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-c", _SENDER, endpoint], check=True, timeout=30, env=env)
    assert within(lambda: ("junk/end", 100) in got, 10.0)
    time.sleep(0.2)
    assert got == [("junk/small", 100), ("junk/frame", 307_200), ("junk/end", 100)]
    assert DEFAULT_MAX_MESSAGE_SIZE < 2_000_000
    # dropped by Zenoh on the link, not let through to the bus's own size check
    assert router.stats.rejected["raw"] == 0
