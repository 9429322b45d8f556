"""The Zenoh layer on loopback: real router and client sessions in one process."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from schemas import MESSAGE_TYPES, MapUpdate, Message, Scan, keys
from schemas.bus import Bus, BusError
from tests.examples import all_examples, scan
from tests.waiting import within


def key_for(name: str) -> str:
    return keys.KEY_TEMPLATES[name].replace("<id>", "r1")


def test_every_message_type_crosses_the_bus(router: Bus, endpoint: str) -> None:
    examples = all_examples()
    got: dict[str, Message] = {}
    lock = threading.Lock()
    with Bus.open("client", connect=[endpoint]) as a, Bus.open("client", connect=[endpoint]) as b:
        for name, cls in MESSAGE_TYPES.items():
            def on(key: str, msg: Message, name: str = name) -> None:
                with lock:
                    got[name] = msg
            b.subscribe(key_for(name), cls, on)
        for name in examples:
            assert a.wait_for_subscribers(key_for(name))
        for name, msg in examples.items():
            a.publish(key_for(name), msg, block=True)
        assert within(lambda: len(got) == len(examples), 5.0)
    assert got == examples


def test_garbage_is_counted_and_not_delivered(router: Bus, endpoint: str) -> None:
    delivered: list[Scan] = []
    with Bus.open("client", connect=[endpoint]) as a:
        router.subscribe(keys.ALL_SCANS, Scan, lambda k, m: delivered.append(m))
        assert a.wait_for_subscribers(keys.robot_scan("r3"))
        a.session.put(keys.robot_scan("r1"), b"\x93garbage")
        a.session.put(keys.robot_scan("r2"), b"")
        a.publish(keys.robot_scan("r3"), scan("r3"), block=True)
        assert within(lambda: len(delivered) == 1 and router.stats.rejected["Scan"] == 2, 5.0)
    assert delivered[0].robot_id == "r3"
    assert "mrslam/robot/r" in router.stats.last_error


def test_a_failing_handler_does_not_stop_delivery(router: Bus, endpoint: str) -> None:
    seen: list[int] = []

    def handler(key: str, msg: Scan) -> None:
        seen.append(msg.seq)
        if msg.seq == 0:
            raise RuntimeError("boom")

    with Bus.open("client", connect=[endpoint]) as a:
        router.subscribe(keys.ALL_SCANS, Scan, handler)
        assert a.wait_for_subscribers(keys.robot_scan("r1"))
        for i in range(3):
            a.publish(keys.robot_scan("r1"), scan(seq=i), block=True)
        assert within(lambda: len(seen) == 3, 5.0)
    assert router.stats.callback_errors["Scan"] == 1


def test_a_client_can_wait_until_someone_subscribes(router: Bus, endpoint: str) -> None:
    got: list[Scan] = []
    with Bus.open("client", connect=[endpoint]) as a, Bus.open("client", connect=[endpoint]) as b:
        assert not a.wait_for_subscribers(keys.robot_scan("r1"), timeout_s=0.3)
        b.subscribe(keys.ALL_SCANS, Scan, lambda k, m: got.append(m))
        assert a.wait_for_subscribers(keys.robot_scan("r1"))
        assert not a.wait_for_subscribers(keys.robot_scan("r1") + "/other", timeout_s=0.2)
        a.publish(keys.robot_scan("r1"), scan("r1"), block=True)
        assert within(lambda: len(got) == 1, 5.0)


def test_latest_map_queryable(router: Bus, endpoint: str) -> None:
    latest = all_examples()["MapUpdate"]
    router.serve(keys.SERVER_MAP, lambda: [latest])
    with Bus.open("client", connect=[endpoint]) as a:
        replies = a.get(keys.SERVER_MAP, MapUpdate, timeout_s=3.0)
    assert replies == [latest]


@pytest.mark.e2e
def test_liveliness_appears_and_vanishes_when_a_client_is_killed(
        router: Bus, endpoint: str) -> None:
    events: list[tuple[str, bool]] = []
    router.watch_alive(keys.ALL_ALIVE, lambda k, alive: events.append((k, alive)))
    code = (
        "import time, sys\n"
        "from schemas.bus import Bus\n"
        "from schemas import keys\n"
        f"bus = Bus.open('client', connect=['{endpoint}'])\n"
        "bus.declare_alive(keys.robot_alive('r9'))\n"
        "print('up', flush=True)\n"
        "time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "up"
        assert within(lambda: ("mrslam/robot/r9/alive", True) in events, 5.0)
        proc.kill()
        proc.wait(timeout=5)
        t_kill = time.monotonic()
        assert within(lambda: ("mrslam/robot/r9/alive", False) in events, 5.0)
        assert time.monotonic() - t_kill < 5.0
    finally:
        proc.kill()


def test_unreachable_router_is_a_bus_error() -> None:
    from schemas.bus import free_local_endpoint

    with pytest.raises(BusError, match="client session"):
        Bus.open("client", connect=[free_local_endpoint()], connect_timeout_ms=300)


def test_bad_listen_endpoint_is_a_bus_error() -> None:
    with pytest.raises(BusError):
        Bus.open("router", listen=["tcp/256.1.1.1:1"])


def test_clients_retry_their_router_soon_unless_their_config_file_says(tmp_path: Path) -> None:
    """A client that lost its router (a server restarting) tries again within a second, not
    after Zenoh's default back-off of up to 4 s; a config file's own retry setting is kept."""
    import json

    from schemas.bus import RECONNECT_RETRY, zenoh_config

    conf = zenoh_config("client", connect=["tcp/127.0.0.1:7447"])
    assert json.loads(conf.get_json("connect/retry")) == RECONNECT_RETRY
    own = tmp_path / "zenoh.json5"
    own.write_text('{ connect: { retry: { period_init_ms: 5000 } } }')
    conf = zenoh_config("client", connect=["tcp/127.0.0.1:7447"], config_file=str(own))
    assert json.loads(conf.get_json("connect/retry"))["period_init_ms"] == 5000


def test_a_polled_subscription_holds_what_came_until_drained_with_its_receipt(
        router: Bus, endpoint: str) -> None:
    """What a polled subscription holds is there as soon as it arrives, whatever Python's
    threads are doing, with the router's own receipt; garbage is counted, not kept."""
    polled = router.subscribe_polled(keys.ALL_SCANS, Scan)
    with Bus.open("client", connect=[endpoint]) as client:
        assert client.wait_for_subscribers(keys.robot_scan("r1"), 5.0)
        t0 = time.time_ns()
        for seq in range(5):
            client.publish(keys.robot_scan("r1"), scan("r1", seq=seq), block=True)
        client.session.put(keys.robot_scan("r1"), b"\x00garbage")
        got: list[tuple[Scan, int]] = []
        assert within(lambda: bool(got.extend(polled.drain())) or len(got) >= 5, 5.0)
    assert [m.seq for m, _ in got] == [0, 1, 2, 3, 4]
    receipts = [t for _, t in got]
    assert receipts == sorted(receipts) and t0 <= receipts[0] <= time.time_ns()
    assert polled.drain() == [] and router.stats.rejected["Scan"] == 1
