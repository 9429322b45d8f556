"""Oversized messages are dropped where they arrive (issue 20, item 3): the cap sits above our
largest legitimate messages, and a garbage payload over it neither arrives nor breaks the link."""

from __future__ import annotations

import os
import time

import numpy as np
import zenoh

from schemas.bus import DEFAULT_MAX_MESSAGE_SIZE, Bus
from schemas.codec import encode
from schemas.config import BusConfig
from schemas.messages import MapUpdate
from schemas.sim import SimImage
from tests.waiting import within


def test_the_cap_is_well_above_our_largest_messages() -> None:
    rng = np.random.default_rng(0)
    frame = SimImage(robot_id="r1", width=640, height=480, fx=500.0, fy=500.0, cx=320.0,
                     cy=240.0, data=rng.integers(0, 256, 640 * 480, dtype=np.uint8).tobytes())
    # a 900x900 map whose every cell is noise: zlib cannot shrink it much (real maps: ~100 kB)
    noise = MapUpdate.from_grid(rng.integers(-1, 101, (900, 900)).astype(np.int8),
                                team_id="t1", robot_ids=["r1", "r2", "r3", "r4", "r5"],
                                resolution_m=0.05, origin=(0.0, 0.0, 0.0))
    assert 4 * len(encode(frame)) < DEFAULT_MAX_MESSAGE_SIZE
    assert 2 * len(encode(noise)) < DEFAULT_MAX_MESSAGE_SIZE
    assert DEFAULT_MAX_MESSAGE_SIZE < 2_000_000   # the garbage payloads are over it


def test_oversized_payloads_never_reach_a_subscriber_and_the_link_survives(
        router: Bus, endpoint: str) -> None:
    at_router: list[tuple[str, int]] = []
    router.subscribe_raw("junk/**", lambda k, b: at_router.append((k, len(b))))
    under = DEFAULT_MAX_MESSAGE_SIZE - 4096
    with Bus.open("client", connect=[endpoint]) as sender, \
            Bus.open("client", connect=[endpoint]) as other:
        at_client: list[tuple[str, int]] = []
        other.subscribe_raw("junk/**", lambda k, b: at_client.append((k, len(b))))
        assert sender.wait_for_subscribers("junk/x")
        time.sleep(0.3)   # the second subscriber's declaration reaches the router too
        block = zenoh.CongestionControl.BLOCK
        # several in a row: with shared memory on, Zenoh's link dropped only the first
        for key, size in (("junk/big", 2_000_000), ("junk/small", 100), ("junk/big", 2_000_000),
                          ("junk/big", 2_000_000), ("junk/under", under), ("junk/end", 100)):
            sender.session.put(key, os.urandom(size), congestion_control=block)
        end = ("junk/end", 100)
        assert within(lambda: end in at_router and end in at_client, 10.0)
        want = [("junk/small", 100), ("junk/under", under), ("junk/end", 100)]
        assert at_router == want and at_client == want
        # Zenoh's own limit drops them on the link (all of them, with shared memory off);
        # those that got through were dropped by the bus, by size, and counted
        rejected = other.stats.rejected["raw"] + router.stats.rejected["raw"]
        assert rejected == 0 or "over bus.max_message_size" in (
            other.stats.last_error + router.stats.last_error)


def test_publishing_over_the_configured_cap_is_counted(router: Bus, endpoint: str) -> None:
    frame = SimImage(robot_id="r1", width=640, height=480, fx=500.0, fy=500.0, cx=320.0,
                     cy=240.0, data=bytes(640 * 480))
    cfg = BusConfig(connect=[endpoint], max_message_size=65_536)
    with Bus.from_config(cfg) as small:
        small.publish("junk/frame", frame)
        assert small.stats.oversized == {"SimImage": 1}
        assert small.stats.as_dict()["oversized"] == {"SimImage": 1}


def test_a_subscriber_drops_by_size_what_the_link_let_through(router: Bus, endpoint: str
                                                               ) -> None:
    """The bus's own check, which catches what Zenoh's link limit misses: a session whose
    link takes anything, wrapped with a 64 kB cap."""
    from schemas.bus import zenoh_config

    conf = zenoh_config("client", connect=[endpoint], max_message_size=1 << 30)
    got: list[int] = []
    with Bus(zenoh.open(conf), max_message_size=65_536) as capped:
        capped.subscribe_raw("junk/**", lambda k, b: got.append(len(b)))
        assert router.wait_for_subscribers("junk/x")
        block = zenoh.CongestionControl.BLOCK
        for size in (80_000, 100, 80_000, 65_536):
            router.session.put("junk/x", os.urandom(size), congestion_control=block)
        assert within(lambda: len(got) == 2, 10.0)
        time.sleep(0.3)
        assert got == [100, 65_536]
        assert capped.stats.rejected["raw"] == 2
        assert "80000 bytes, over bus.max_message_size (65536)" in capped.stats.last_error
