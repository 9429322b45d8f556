"""The agent obeys the server it is bound to, and counts what it ignores (issue 20, item 4).

Without access rules anyone who reaches the router can publish on a robot's ``cmd_vel``; these
tests play a stranger doing so on loopback against a real agent and a real Zenoh router.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from robot_agent.backend import Backend, Odometry, Sweep
from robot_agent.command_gate import CommandGate
from robot_agent.config import AgentConfig
from robot_agent.runtime import Agent
from schemas import VelocityCommand, keys
from schemas.bus import Bus
from schemas.codec import encode
from tests.waiting import within

S = 1_000_000_000


def cmd(stamp_s: float, robot_id: str = "r1", v: float = 0.1) -> VelocityCommand:
    return VelocityCommand(robot_id=robot_id, stamp_ns=round(stamp_s * S), v_mps=v,
                           omega_rps=0.0, ttl_s=5.0)


# -- the rules, one by one -------------------------------------------------------------------
def test_a_command_needs_a_server_and_must_come_from_it() -> None:
    gate = CommandGate("r1")
    assert gate.check(cmd(1.0), "aa", 1 * S) == "no_server"
    assert gate.server_holder("aa", True) == "aa"
    assert gate.check(cmd(1.0, robot_id="r2"), "aa", 1 * S) == "other_robot"
    assert gate.check(cmd(1.0), None, 1 * S) == "not_from_server"     # no source given
    assert gate.check(cmd(1.0), "bb", 1 * S) == "not_from_server"
    assert gate.check(cmd(1.0), "aa", 1 * S) is None


def test_the_first_holder_stays_bound_until_its_token_goes() -> None:
    gate = CommandGate("r1")
    gate.server_holder("aa", True)
    assert gate.server_holder("bb", True) == "aa"          # a later claimant is not obeyed
    assert gate.check(cmd(1.0), "bb", 1 * S) == "not_from_server"
    assert gate.server_holder("aa", False) == "bb"          # the server went: the next one
    assert gate.check(cmd(1.0), "bb", 1 * S) is None
    assert gate.server_holder("bb", False) is None
    assert gate.check(cmd(1.0), "bb", 1 * S) == "no_server"


def test_stamps_must_be_on_the_robot_clock_and_in_order() -> None:
    gate = CommandGate("r1", max_age_s=10.0, max_ahead_s=1.0)
    gate.server_holder("aa", True)
    now = 100 * S
    assert gate.check(cmd(101.5), "aa", now) == "from_future"
    assert gate.check(cmd(89.0), "aa", now) == "stale"
    assert gate.check(cmd(0.0), "aa", now) == "stale"        # a stranger's stamp-0 command
    assert gate.check(cmd(99.0), "aa", now) is None
    assert gate.check(cmd(99.0), "aa", now) is None          # the same scan answered twice
    assert gate.check(cmd(98.9), "aa", now) == "out_of_order"
    # the robot's clock goes back (a simulator restarted): the order starts afresh
    assert gate.check(cmd(1.0), "aa", 2 * S) is None
    # a new server session: its commands start a new order
    gate.check(cmd(1.9), "aa", 2 * S)
    gate.server_holder("cc", True)
    gate.server_holder("aa", False)
    assert gate.check(cmd(1.5), "cc", 2 * S) is None


def test_a_split_server_is_obeyed_through_the_worker_that_serves_the_robot() -> None:
    gate = CommandGate("r1")
    for w, zid in enumerate(("aa", "bb")):       # each worker holds the server's token
        gate.server_holder(zid, True)
        gate.worker_session(w, zid, True)
    assert gate.server == "aa"                   # nobody serves r1 yet: the first holder
    assert gate.owner(1, True) == "bb"
    assert gate.check(cmd(1.0), "aa", 2 * S) == "not_from_server"
    assert gate.check(cmd(1.0), "bb", 2 * S) is None
    # its team moves to worker 0, which claims it while worker 1 still holds its token
    assert gate.owner(0, True) == "aa"
    assert gate.check(cmd(1.1), "bb", 2 * S) == "not_from_server"
    assert gate.check(cmd(0.9), "aa", 2 * S) is None     # a new server: a new order
    assert gate.owner(1, False) == "aa"
    assert gate.owner(3, True) == "aa"           # a worker whose session is not known yet
    # the serving worker's session goes: the next owner whose session is known, else the
    # first holder of the server's token
    assert gate.worker_session(0, "aa", False) == "aa"
    gate.server_holder("aa", False)
    assert gate.server == "bb"
    gate.server_holder("dd", True)
    assert gate.worker_session(3, "dd", True) == "dd"
    # a later session that claims to be worker 3, or one without the server's token, is not
    # obeyed while worker 3's first session lives
    gate.server_holder("ee", True)
    assert gate.worker_session(3, "ee", True) == "dd"
    assert gate.worker_session(0, "ff", True) == "dd"
    assert gate.owner(0, True) == "dd"          # "ff" does not hold the server's token
    assert gate.worker_session(3, "dd", False) == "ee"


# -- on the wire -----------------------------------------------------------------------------
class StillBase:
    """A base that records what it is told; the robot's clock is the wall clock."""

    def __init__(self) -> None:
        self.velocities: list[tuple[float, float]] = []

    def odometry_at(self, stamp_ns: int) -> Odometry | None:
        return Odometry(stamp_ns, (0.0, 0.0, 0.0))

    def set_velocity(self, v_mps: float, omega_rps: float) -> None:
        self.velocities.append((v_mps, omega_rps))


class NoLidar:
    def start(self, on_sweep: Callable[[Sweep], None]) -> None:
        pass


@pytest.fixture
def agent(router: Bus, endpoint: str) -> Iterator[tuple[Agent, StillBase]]:
    base = StillBase()
    cfg = AgentConfig.model_validate({"robot_id": "r1", "bus": {"connect": [endpoint]},
                                      "detector": {"enabled": False}})
    stop = threading.Event()
    with Bus.from_config(cfg.bus) as bus:
        a = Agent(cfg, bus, Backend(lidar=NoLidar(), base=base, camera=None,
                                    now_ns=time.time_ns))
        a.start()
        thread = threading.Thread(target=a.run, args=(stop,))
        thread.start()
        try:
            yield a, base
        finally:
            stop.set()
            thread.join(timeout=10)


def test_a_strangers_commands_are_ignored_and_counted(
        router: Bus, endpoint: str, agent: tuple[Agent, StillBase]) -> None:
    a, base = agent
    router.declare_alive(keys.SERVER_ALIVE)     # the router plays the server
    assert within(lambda: a.gate.server == router.zid, 10.0)
    key = keys.robot_cmd_vel("r1")
    with Bus.open("client", connect=[endpoint]) as stranger:
        assert stranger.wait_for_subscribers(key)
        n = 50   # a second at 50 Hz: what drove a robot in circles before
        for _ in range(n):
            stranger.publish(key, VelocityCommand(robot_id="r1", stamp_ns=time.time_ns(),
                                                  v_mps=0.5, omega_rps=2.0, ttl_s=5.0))
            time.sleep(0.02)
        assert within(lambda: a.counters["commands_ignored_not_from_server"] == n, 10.0)
        # nor does a plain Zenoh put on the key (no source) or a stale stamp from the server
        stranger.session.put(key, encode(cmd(time.time_ns() / S, v=0.5)))
        router.publish(key, cmd(time.time_ns() / S - 60.0, v=0.5))
        assert within(lambda: a.counters["commands_ignored"] == n + 2, 10.0)
        assert a.counters["commands_ignored_stale"] == 1
    # the server's own command is obeyed
    router.publish(key, cmd(time.time_ns() / S, v=0.2))
    assert within(lambda: a.counters["commands_received"] == 1, 10.0)
    assert all(v != 0.5 for v, _ in base.velocities) and (0.2, 0.0) in base.velocities
    summary: dict[str, Any] = a.summary()
    assert summary["commands_ignored"] == n + 2 and a.errors() >= n + 2


def test_each_robot_obeys_the_worker_that_serves_it(
        router: Bus, endpoint: str, agent: tuple[Agent, StillBase]) -> None:
    """Two workers of a split server hold the server's token; r1's agent obeys the one whose
    owner token names r1, then the other once r1's team has moved to it."""
    a, base = agent
    key = keys.robot_cmd_vel("r1")
    with Bus.open("client", connect=[endpoint]) as w0, \
            Bus.open("client", connect=[endpoint]) as w1:
        for w, bus in enumerate((w0, w1)):
            bus.declare_alive(keys.cluster_worker(w))
            bus.declare_alive(keys.SERVER_ALIVE)
        owner1 = w1.declare_token(keys.cluster_owner("r1", 1))
        w0.declare_token(keys.cluster_owner("r7", 0))        # another robot's: no matter
        assert within(lambda: a.gate.server == w1.zid, 10.0)
        for bus in (w0, w1):
            assert bus.wait_for_subscribers(key)
        w0.publish(key, cmd(time.time_ns() / S, v=0.5))
        w1.publish(key, cmd(time.time_ns() / S, v=0.2))
        assert within(lambda: a.counters["commands_received"] == 1, 10.0)
        assert within(lambda: a.counters["commands_ignored_not_from_server"] == 1, 10.0)
        assert (0.2, 0.0) in base.velocities and all(v != 0.5 for v, _ in base.velocities)
        # r1's team moves to worker 0: it claims r1, worker 1 lets its token go
        w0.declare_token(keys.cluster_owner("r1", 0))
        w1.undeclare(owner1)
        assert within(lambda: a.gate.server == w0.zid and a.gate.owned_by == {0}, 10.0)
        w1.publish(key, cmd(time.time_ns() / S, v=0.4))
        w0.publish(key, cmd(time.time_ns() / S, v=0.3))
        assert within(lambda: a.counters["commands_received"] == 2, 10.0)
        assert within(lambda: a.counters["commands_ignored_not_from_server"] == 2, 10.0)
        assert (0.3, 0.0) in base.velocities and all(v != 0.4 for v, _ in base.velocities)
