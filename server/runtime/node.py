"""The server's one bus module: Zenoh in, ``ServerCore`` in a worker thread, Zenoh out.

Zenoh delivers scans on its own threads; they are admitted (robot, key, clock and stamp order:
``server.runtime.registry``), their stamps mapped into the server's time, queued per robot,
and handed to the core by a single worker thread, so the core needs no locks. Each command goes back
stamped with the robot's own stamp of its scan. The worker also publishes maps, robot states
and events on their periods, and forgets robots that went silent.

In a lockstep simulation the worker takes a step at a time (``server.runtime.lockstep``): it waits
until every live robot's scan of the step is in, then hands the core the step's messages in
robot order — scans, then tag sightings — so the run is the same every time.

An operator's order (``operate``, from the console) goes ahead of every queued message: the
worker journals it and hands it to the core next. A stop also holds the robots' commands at
zero from the moment it is asked, so a scan being processed meanwhile cannot move them.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import msgspec

from schemas import Scan, SimClock, TagDetections, keys
from schemas.bus import Bus, Polled
from schemas.ratelog import RateLimitedLog
from server.command.operator import OperatorCommand
from server.config import ServerConfig
from server.core import ServerCore
from server.runtime import heap, moves
from server.runtime.clock import ClockPolicy, ServerClock
from server.runtime.cluster import Cluster, Handover
from server.runtime.inbox import NEWCOMER, TRUSTED, Inbox
from server.runtime.journal import JournalWriter
from server.runtime.keeper import StateKeeper
from server.runtime.lockstep import StepBarrier
from server.runtime.outputs import OutputPacer, Pause, Spread
from server.runtime.planner_pool import Pools
from server.runtime.publish import Publisher
from server.runtime.registry import AdmissionPolicy, Refused, RobotRegistry
from server.runtime.work import (
    AdoptWork,
    AliveWork,
    GiveWork,
    OrderWork,
    ScanWork,
    TagsWork,
    Work,
    robot_of,
)
from server.runtime.writer import BackgroundWriter

log = logging.getLogger(__name__)


#: the worker, stopping, waits this long for a snapshot being taken [s] (``ServerNode.stop``
#: waits 10 s for the worker)
STOP_SNAPSHOT_WAIT_S = 8.0


class ServerNode:
    def __init__(self, bus: Bus, cfg: ServerConfig, core: ServerCore | None = None,
                 journal: JournalWriter | None = None,
                 outputs: Callable[[ServerNode], Callable[[Pause], None] | None] | None = None
                 ) -> None:
        """``journal``: where every processed message is appended first; ``outputs``: called
        by the worker every ``outputs_period_s``, or less often where that would take more than
        4 % of a core (``OutputPacer``; nowhere else touches the core), to
        gather what to write; the writing it returns runs on the writer thread."""
        self.bus = bus
        self.cfg = cfg
        self.core = core or ServerCore(cfg)
        #: the journal and the snapshots, through a full disk (``server.runtime.keeper``)
        self.journal = StateKeeper(journal) if journal is not None else None
        self.outputs = outputs
        self.clock = ServerClock(cfg.clock.source)
        a, c = cfg.admission, cfg.clock
        self.registry = RobotRegistry(AdmissionPolicy(
            allowed=frozenset(cfg.robots) if cfg.robots is not None else None,
            probation=a.probation_messages, forget_after_ns=round(a.forget_after_s * 1e9),
            max_newcomers=a.max_newcomers, newcomers_per_s=a.newcomers_per_s,
            newcomer_burst=a.newcomer_burst,
            clock=ClockPolicy(round(c.max_skew_s * 1e9), c.rebase_after,
                              round(c.window_s * 1e9), round(c.tolerance_s * 1e9))))
        self.errors = 0
        self.foreign_commands: dict[str, int] = {}   # robot -> commands others published
        self._inbox = Inbox(cfg.queue_per_robot)
        self.dropped = self._inbox.dropped
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self.publisher = Publisher(bus, cfg.states_period_s)
        self._lockstep = False   # the simulator's clock says it steps in lockstep
        self._sim_clock: Polled[SimClock] | None = None   # its clock messages, if sim
        self._barrier = StepBarrier(cfg.clock.step_barrier_s)
        self._errlog = RateLimitedLog(log)
        self._worker = threading.Thread(target=self._work, name="server-core", daemon=True)
        #: where the core's slow work runs, given to it once (none in lockstep)
        self.pools = Pools(cfg.planner_processes, cfg.teams.map_match, lambda: self._lockstep)
        self.core.use_pools(self.pools.planner, self.pools.matcher)
        self._writer = BackgroundWriter(self._write_failed)
        self._outputs_writer = BackgroundWriter(self._write_failed, name="server-outputs")
        self._spread = Spread()
        #: one worker of several (``server.runtime.cluster``), or None: the only server
        self.cluster = None if cfg.cluster.worker is None else Cluster(
            bus, cfg.cluster, self._on_give, self._on_handover)
        if self.cluster is not None:
            self.cluster.resumed = set(self.core.robots)
        #: operator's orders waiting for the worker, each with the answer the asker waits on
        self._orders: deque[OrderWork] = deque()
        #: stops asked and not yet taken by the core ("*": every robot): commands are zero
        self._stops_asked: set[str] = set()
        #: the core's orders as the console shows them (replaced whole by the worker)
        self.orders_view: dict[str, Any] = self.core.orders.view()
        self._held: dict[str, list[tuple[str, int, Any]]] = {}   # robots whose team is coming
        #: the last scans of robots other workers serve (``moves.routed``)
        self._recent: dict[str, deque[tuple[str, int, Any]]] = {}
        #: each robot's own stamp of the last scan the core took (a team that moves here
        #: brings the giver's: what it had not processed yet is taken from those held here)
        self._own_stamps: dict[str, int] = {}
        #: the worker's handler of each kind of item
        self._handlers: dict[type, Callable[[Any], None]] = {
            ScanWork: self._take_scan, TagsWork: self._take_tags, AliveWork: self._take_alive,
            GiveWork: functools.partial(moves.give, self),
            AdoptWork: functools.partial(moves.adopt, self), OrderWork: self._operate}

    # -- inputs (Zenoh threads) ------------------------------------------------------------
    def start(self) -> None:
        if self.cluster is not None:
            # a worker first: an agent that sees the server's token knows whose it is
            self.cluster.start()
        self.bus.declare_alive(keys.SERVER_ALIVE)
        if self.clock.source == "sim":
            # drained before each message is placed in simulated time (and by the worker):
            # a callback of its own could run after a scan that came later
            self._sim_clock = self.bus.subscribe_polled(keys.SIM_CLOCK, SimClock)
        self.bus.subscribe_received(keys.ALL_SCANS, Scan, self._on_message)
        self.bus.subscribe_received(keys.ALL_TAGS, TagDetections, self._on_message)
        self.bus.watch_alive(keys.ALL_ALIVE, self._on_alive)
        # only this server commands robots: anyone else who does is counted (on a network the
        # access rules stop them in the router, before they get here: deploy/README.md)
        self.bus.watch_senders(keys.ALL_CMD_VEL, self._on_foreign_command)
        self.publisher.serve()
        self._worker.start()

    def _take_sim_clock(self) -> None:
        """The simulator's clock messages that came since the last call (the caller holds
        ``_cv``)."""
        if self._sim_clock is None:
            return
        for msg, received_ns in self._sim_clock.drain():
            self.clock.on_sim_clock(msg.stamp_ns, received_ns, msg.dt_ns,
                                    0.0 if msg.lockstep else msg.real_time_factor)
            self._lockstep = msg.lockstep

    def _on_message(self, key: str, msg: Scan | TagDetections, received_ns: int) -> None:
        stream = "scan" if isinstance(msg, Scan) else "tags"
        with self._cv:
            self._take_sim_clock()   # every clock message that came before this one
            # the receipt as the router stamped it, not when this callback got to run
            server_ns, slack_ns = self.clock.receive_ns(received_ns)
            try:
                ready = self.registry.admit(keys.robot_id_of(key), msg.robot_id, stream,
                                            msg.stamp_ns, server_ns, msg, slack_ns,
                                            lambda: self.clock.receive_ns(received_ns)[0])
            except Refused:
                return
            if self.cluster is not None:
                ready = moves.routed(self, msg.robot_id, ready)
            self._enqueue(msg.robot_id, ready)

    # -- a team moving between workers (Zenoh threads) -------------------------------------
    def _on_give(self, query: Any, robots: list[str]) -> None:
        self._queue_control("#give:", GiveWork(query, robots))

    def _on_handover(self, h: Handover) -> None:
        self._queue_control("#adopt:", AdoptWork(h))

    def _queue_control(self, name: str, item: Work) -> None:
        with self._cv:
            self._inbox.put_control(name, item)
            self._cv.notify()

    def _enqueue(self, rid: str, ready: list[tuple[str, int, Any]]) -> None:
        """Queue admitted messages (stamps in server time), in the turn of robots the server
        trusts or of newcomers (``server.runtime.inbox``); the caller holds ``_cv``."""
        tier = TRUSTED if self.registry.trusted(rid) else NEWCOMER
        for stream, stamp_ns, msg in ready:
            self.clock.on_accepted(stamp_ns)
            # the core works in server time; the robot's own stamp goes back in its command
            mapped = msgspec.structs.replace(msg, stamp_ns=stamp_ns)
            if stream == "scan":
                self._inbox.put(rid, ScanWork(mapped, msg.stamp_ns), tier)
            else:
                self._inbox.put(f"#tags:{rid}", TagsWork(mapped), tier)
        if ready:
            self._cv.notify()

    def _on_foreign_command(self, key: str, sender: str | None) -> None:
        if self.cluster is not None and self.cluster.is_worker(sender):
            return      # another worker's robot
        rid = keys.robot_id_of(key) or "?"
        with self._cv:
            self.foreign_commands[rid] = self.foreign_commands.get(rid, 0) + 1
            n = sum(self.foreign_commands.values())
        self._errlog.log(logging.WARNING, "foreign-command", "a command for robot %s came from "
                         "session %s, not this server (#%d; its agent ignores it)", rid,
                         sender or "unknown", n)

    def _on_alive(self, key: str, alive: bool) -> None:
        rid = keys.robot_id_of(key)
        if rid is None:
            return
        with self._cv:
            changed, ready = self.registry.set_alive(rid, alive, self.clock.reference_ns())
            if changed:
                self._queue_alive(rid, alive)
            self._enqueue(rid, ready)

    def _queue_alive(self, rid: str, alive: bool) -> None:
        """(the caller holds ``_cv``)"""
        self._inbox.put_control(f"#alive:{rid}", AliveWork(rid, alive))
        self._cv.notify()

    # -- the worker ------------------------------------------------------------------------
    def _next(self, timeout_s: float) -> list[Work]:
        """The next item; in lockstep, the next step's messages."""
        with self._cv:
            self._take_sim_clock()
            if not self._inbox and not self._orders and not self._cv.wait_for(
                    lambda: bool(self._inbox or self._orders), timeout_s):
                return []
            self._take_sim_clock()
            if self._orders:
                return [self._orders.popleft()]
            if self._lockstep:
                return [item for _, item in self._barrier.take(self._inbox, self._cv,
                                                               self._live_robots())]
            taken = self._inbox.take()
            return [] if taken is None else [taken[1]]

    # -- the worker's items (``server.runtime.work``) -------------------------------------
    def _take_alive(self, item: AliveWork) -> None:
        if self.journal is not None:
            self.journal.alive(item.robot_id, item.alive, self.clock.now_ns())
        self.core.set_alive(item.robot_id, item.alive)

    def _take_tags(self, item: TagsWork) -> None:
        if self.journal is not None:
            self.journal.tags(item.tags)
        self.core.on_tags(item.tags)

    def _take_scan(self, item: ScanWork) -> None:
        scan, rid = item.scan, item.scan.robot_id
        if self.cluster is not None and not self.cluster.serves(rid):
            return      # its team went to another worker meanwhile
        # (in lockstep the step's own time: the simulator's clock message may come before or
        # after the step's scans)
        now = scan.stamp_ns if self._lockstep else (
            self.clock.now_ns() if self.clock.source != "stamps" else None)
        if self.journal is not None:
            self.journal.scan(scan, now)
        cmd = self.core.on_scan(scan, now)
        self._own_stamps[rid] = item.own_stamp_ns
        if self._stops_asked and (rid in self._stops_asked or "*" in self._stops_asked):
            cmd = msgspec.structs.replace(cmd, v_mps=0.0, omega_rps=0.0)
        self.bus.publish(keys.robot_cmd_vel(rid),
                         msgspec.structs.replace(cmd, stamp_ns=item.own_stamp_ns), block=True)

    def _live_robots(self) -> set[str]:
        """Robots alive by their liveliness token, or by the core (worker thread)."""
        return {rid for rid, r in self.core.robots.items() if r.alive} | {
            rid for rid, rec in self.registry.robots.items() if rec.alive}

    def _work(self) -> None:
        next_forget = 0.0
        next_outputs = time.monotonic() + self.cfg.outputs_period_s
        pacer = OutputPacer(self.cfg.outputs_period_s)
        next_snapshot = time.monotonic() + self.cfg.snapshot_period_s
        while not self._stop.is_set():
            for item in self._next(0.1):
                try:
                    self._handlers[type(item)](item)
                except Exception as e:
                    # one robot's failure must not stop the server for the others
                    self.errors += 1
                    self._errlog.log(logging.ERROR, type(e).__name__, "processing %s for %s "
                                     "failed", type(item).__name__, robot_of(item) or "-",
                                     exc_info=self._errlog.seen[type(e).__name__] <= 3)
            heap.maybe_trim()     # freed memory back to the system, twice a minute at most
            now = time.monotonic()
            if self.journal is not None:
                if self.journal.flush_due(now):
                    self.journal.flush(self._writer)
                if now >= next_snapshot:
                    self.guarded("writing a snapshot", self.snapshot, False)
                    next_snapshot = time.monotonic() + self.journal.snapshot_interval_s(
                        now, self.cfg.snapshot_period_s)
                self.guarded("keeping the state", self.journal.maintain, self.core, self._writer)
            if self.outputs is not None and now >= next_outputs \
                    and not self._outputs_writer.busy("outputs"):
                self.guarded("gathering the outputs", self._outputs, pacer)
                next_outputs = now + pacer.next_in()
            if now >= next_forget:
                next_forget = now + 1.0
                if self.cluster is not None:
                    for rid in self.cluster.tick():
                        self.guarded("leaving a robot to another worker", moves.drop, self,
                                     rid)
                with self._cv:
                    for rid in self.registry.forget_silent(self.clock.now_ns()):
                        self._queue_alive(rid, False)
                        self._recent.pop(rid, None)    # another worker's robot, gone quiet
            try:
                self.publisher.tick(self.core, self.clock.now_ns())
            except Exception:
                self.errors += 1
                log.exception("publishing server outputs failed")
        # a snapshot still being taken dies with the thread that forked it (the child's
        # parent-death signal is the thread's, not the process's): it is waited for here
        if self._writer.busy("snapshot"):
            self._writer.drain(STOP_SNAPSHOT_WAIT_S)

    def _outputs(self, pacer: OutputPacer) -> None:
        assert self.outputs is not None
        t0 = time.thread_time()
        job = self.outputs(self)      # gathered here; written by the outputs' thread
        pacer.gather_cpu_s = time.thread_time() - t0
        if job is None:
            return
        write = job

        def spread() -> None:
            self._spread.begin()
            write(self._spread)

        self._outputs_writer.submit("outputs", pacer.timed_write(spread))

    def health(self) -> dict[str, Any]:
        """For the console (any thread): per robot the scans accepted and dropped, the
        operator's orders, and whether the state is being written."""
        with self._cv:
            scans = {rid: rec.accepted.get("scan", 0) for rid, rec in self.registry.robots.items()}
        state = None if self.journal is None else self.journal.view()
        return {"scans": scans, "dropped": dict(self.dropped), "orders": self.orders_view,
                "state": state}

    # -- the operator's orders ---------------------------------------------------------------
    def operate(self, cmd: OperatorCommand) -> Future[tuple[int, str]]:
        """Queue an operator's order ahead of everything else (any thread); the future gives
        the core's answer: (200, what it did), or a refusal's status and why
        (``ServerCore.operate``)."""
        answer: Future[tuple[int, str]] = Future()
        with self._cv:
            if cmd.action == "stop":
                self._stops_asked.add(cmd.robot_id or "*")
            self._orders.append(OrderWork(cmd, answer))
            self._cv.notify()
        return answer

    def _operate(self, item: OrderWork) -> None:
        """(the worker) Journal the order, then hand it to the core."""
        cmd, answer = item.command, item.answer
        try:
            now = self.clock.now_ns()
            if self.journal is not None:
                self.journal.operator(cmd, now)
            result = self.core.operate(cmd, now)
        except Exception as e:
            answer.set_exception(e)
            raise
        finally:
            if cmd.action == "stop":
                with self._cv:
                    self._stops_asked.discard(cmd.robot_id or "*")
            self.orders_view = self.core.orders.view()
        answer.set_result(result)
        log.warning("operator: %s", result[1])

    def snapshot(self, wait: bool = True) -> None:
        """Snapshot the core as of the journal's next entry (worker thread, or after stop).
        Pickled here; compressed and written here (``wait``) or by the writer thread."""
        if self.journal is not None:
            self.journal.snapshot(self.core, self._writer, wait)

    def _write_failed(self, kind: str, e: Exception) -> None:
        """(the writer thread) A background write failed: the state's are the keeper's to
        count; others (the outputs) are counted as errors, logged at a limited rate."""
        if kind in ("journal", "snapshot") and self.journal is not None:
            self.journal.writer_failed(kind, e)
            return
        self.errors += 1
        self._errlog.log(logging.ERROR, f"write:{kind}", "writing the %s failed: %s", kind, e)

    def guarded(self, what: str, fn: Callable[..., None], *args: Any) -> None:
        try:
            fn(*args)
        except Exception as e:   # a full disk must not stop the robots
            self.errors += 1
            self._errlog.log(logging.ERROR, f"{what}:{type(e).__name__}", "%s failed: %s",
                             what, e)

    def leave(self, timeout_s: float) -> list[str]:
        """A worker stopping on purpose hands its teams on (``server.runtime.moves``)."""
        return moves.leave(self, timeout_s)

    def stop(self) -> None:
        self._stop.set()
        if self._worker.is_alive():
            self._worker.join(timeout=10)
        self.pools.stop()   # killed, not waited for: no job holds the stop up
        self._spread.stop()   # a round being written goes on without its pauses
        self._outputs_writer.close()
        self._writer.close()
        if self.journal is not None:
            self.guarded("closing the journal", self.journal.close)

    def summary(self) -> dict[str, Any]:
        return {"registry": self.registry.counters(), "admission": self.registry.totals(),
                "dropped_scans": self.dropped, "foreign_commands": self.foreign_commands,
                "errors": self.errors, "bus": self.bus.stats.as_dict(),
                "lockstep_barrier_timeouts": self._barrier.timeouts,
                "cpu_s": round(time.process_time(), 3),
                "cluster": None if self.cluster is None else self.cluster.summary(),
                "journal": None if self.journal is None else self.journal.summary()}
