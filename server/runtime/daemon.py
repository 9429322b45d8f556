"""``mrslam server``: the central daemon. Opens the Zenoh router, runs the node until it is
interrupted (SIGINT/SIGTERM) or, with ``exit_when_done``, until every team has finished, then
writes its outputs."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from schemas.bus import Bus
from schemas.config_loading import changed_keys, describe_changes
from schemas.stopping import SignalStop
from server.config import ServerConfig
from server.core import ServerCore
from server.knownmap.mapdata import KnownMap
from server.runtime.journal import JournalWriter, replay
from server.runtime.mapfind import leave_map, start_map
from server.runtime.node import ServerNode
from server.runtime.snapshot import Snapshots
from server.slam import render_store

log = logging.getLogger(__name__)

#: a server asked to stop (SIGTERM, SIGINT, SIGHUP) exits this long after at the latest [s],
#: its last outputs written or not: its state survives a SIGKILL anyway (the journal)
STOP_BUDGET_S = 4.0
#: the parts of the configuration a run's state was made with (its SLAM, maps, exploration
#: and teams): a resumed run keeps its own; the rest (bus, admission, clocks, outputs) is
#: this start's
RUN_KEYS = ("slam", "explore", "control", "teams", "map_period_s")


def run(config_path: str | Path | None = None, overrides: dict[str, Any] | None = None,
        stop: threading.Event | None = None, foxglove_port: int | None = None,
        console_port: int | None = None, console_token: str | None = None,
        on_console: Callable[[Any], None] | None = None) -> dict[str, Any]:
    """Run the server until ``stop`` is set, a signal arrives, or (``exit_when_done``) the
    exploration has finished. Returns the summary. ``foxglove_port``: serve the bus's Foxglove
    channels live on that loopback port (``recording.live``). ``console_port``: serve the
    operator console there (``server.console``), with ``console_token`` (else the
    environment's ``MRSLAM_CONSOLE_TOKEN``, else a new one, logged with the address);
    ``on_console`` is called with it once it is up."""
    from schemas.config_loading import load_config, write_resolved
    from server.runtime.outputs import Pause, collect_outputs, write_outputs

    cfg = load_config(ServerConfig, config_path, overrides)
    out = Path(cfg.out) if cfg.out else None
    if out is not None:
        write_resolved(cfg, out, "server_config.yaml")
    stop = stop or threading.Event()
    # a signal stops the server within STOP_BUDGET_S (a worker's handover on top)
    signals = SignalStop(stop, exit_after_s=STOP_BUDGET_S + (
        cfg.cluster.handover_timeout_s if cfg.cluster.worker is not None else 0.0),
        name="the server")
    t0 = time.monotonic()

    def outputs(node: ServerNode) -> Callable[[Pause], None] | None:
        if out is None:
            return None
        gathered = collect_outputs(node.core, {"wall_s": time.monotonic() - t0,
                                               **node.summary(), "resumed": resumed,
                                               "running": True})

        def write(pause: Pause) -> None:
            assert out is not None
            gathered.write(out, pause)

        return write

    b = cfg.bus
    if cfg.cluster.worker is not None and b.mode == "client" and b.connect_timeout_ms is None:
        # a worker started before its router waits for it (as systemd may start them)
        log.info("worker %d: waiting for the router at %s", cfg.cluster.worker,
                 ", ".join(b.connect))
        b = b.model_copy(update={"connect_timeout_ms": -1})
    state = cfg.resolved_state_dir()
    if state is not None:
        render_store.use_folder(state)      # keyframes' map points beside the journal
    # a map that cannot be used is refused before anything starts (MapError: one line)
    known = start_map(cfg, None if state is None else Path(state))
    # open first: robots reconnect while the state loads
    with signals, Bus.from_config(b) as bus:
        core, journal, resumed = _resume(cfg, known)
        if resumed and core.teams and all(t.finished for t in core.teams.values()):
            log.warning("%s", _finished_line(core, cfg))
        node = ServerNode(bus, cfg, core, journal, outputs)
        live = _foxglove_live(bus, foxglove_port)
        console = _console(bus, node, console_port, console_token)
        if console is not None and on_console is not None:
            on_console(console)
        node.start()
        if b.mode == "client":
            log.info("server up (a client of %s)", ", ".join(bus.connecting))
        else:
            log.info("server up (%s listening on %s)", b.mode,
                     ", ".join(bus.listening) or "Zenoh's default endpoints")
        while not stop.wait(0.2):
            if cfg.exit_when_done and node.core.finished:
                time.sleep(0.5)  # let the last commands and events go out
                if node.core.finished:  # not when a merge was undone meanwhile
                    break
        if stop.is_set():   # stopped on purpose: another worker takes the teams on
            node.leave(cfg.cluster.handover_timeout_s)
        node.stop()
        if live is not None:
            live.close()
        if console is not None:
            console.close()
        node.guarded("writing the last snapshot", node.snapshot)
        summary = {"wall_s": time.monotonic() - t0, **node.summary(), "resumed": resumed}
        if console is not None:
            summary["console"] = {**console.counters, "cpu_s": round(console.cpu_s, 3)}
        if out is not None:
            write_outputs(node.core, out, summary)
            node.guarded("writing the mission's map", leave_map, node.core, out, cfg)
    return summary


def _foxglove_live(bus: Bus, port: int | None) -> Any:
    """The Foxglove WebSocket server fed by everything on the bus (the server's own messages
    and the robots'), or None without a port."""
    if port is None:
        return None
    from recording.live import FoxgloveLive
    from schemas import keys

    live = FoxgloveLive(port)
    bus.subscribe_raw(keys.ALL, live.add)
    return live


def _console(bus: Bus, node: ServerNode, port: int | None, token: str | None) -> Any:
    """The operator console fed by the server's outputs, its orders going to ``node``; or
    None without a port."""
    if port is None:
        return None
    import os

    from server.console.service import TOKEN_ENV, Console

    console = Console(port, node.operate, node.health,
                      token=token or os.environ.get(TOKEN_ENV) or None)
    console.attach(bus)
    # the one line an operator needs; the token is in it (the log is the server's own)
    log.warning("console: %s", console.url)
    return console


def _finished_line(core: ServerCore, cfg: ServerConfig) -> str:
    """Why a server resumed on a finished run does nothing: every team had ended, and how."""
    ends = []
    for team in core.teams.values():
        whys = {core.fleet.robots[rid].nav.finished_reason for rid in team.robot_ids
                if rid in core.fleet.robots}
        why = "; ".join(sorted(w for w in whys if w)) or "finished"
        at = "" if team.finished_stamp_ns is None else f" at {_when(team.finished_stamp_ns)}"
        ends.append(f"{team.team_id}: {why}{at}, coverage {team.coverage:.0%}")
    then = ("so the server stops now (exit_when_done)" if cfg.exit_when_done
            else "so its robots are given no more targets")
    return (f"the resumed run had already finished ({'; '.join(ends)}): nothing is left to "
            f"explore, {then}; an empty state_dir (now {cfg.resolved_state_dir()}) starts a "
            "new run")


def _when(stamp_ns: int) -> str:
    """A stamp of the server's clock: seconds of simulated time, or a date (the wall clock)."""
    s = stamp_ns * 1e-9
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(s)) if s > 1e9 else f"{s:.1f} s"


def _resume(cfg: ServerConfig, known: KnownMap | None = None
            ) -> tuple[ServerCore, JournalWriter | None, dict[str, Any]]:
    """The core as the state folder left it — the newest snapshot that reads back, with the
    journal after it replayed — and the journal to go on with (a new segment). A run
    without a snapshot starts on ``known`` (the map it started on: ``start_map``)."""
    state = cfg.resolved_state_dir()
    if state is None:
        return ServerCore(cfg, known=known), None, {}
    render_store.use_folder(state)          # (as ``run`` did already, for the known map's)
    t0 = time.monotonic()
    loaded = Snapshots(state).load()
    core, since = loaded if loaded is not None else (ServerCore(cfg, known=known), 0)
    if loaded is not None and (changes := changed_keys(core.cfg, cfg, RUN_KEYS)):
        log.warning("the configuration differs from the resumed run's in %d setting(s) its "
                    "state was made with, which keep the run's values: %s (an empty state_dir "
                    "starts a run with them)", len(changes), describe_changes(changes))
    report = replay(core, state, from_sequence=since)
    resumed: dict[str, Any] = {}
    if report.entries or loaded is not None:
        resumed = {"snapshot_sequence": since if loaded is not None else None,
                   "segments": report.segments, "entries": report.entries,
                   "replayed": report.entries - report.skipped,
                   "unreadable": report.unreadable, "problems": report.problems,
                   "replay_s": round(report.seconds, 3),
                   "resume_s": round(time.monotonic() - t0, 3),
                   "robots": sorted(core.robots), "teams": sorted(core.teams)}
        log.warning("resumed from %s: snapshot at %s, %d journal message(s) replayed in "
                    "%.1f s (%s); teams %s", state, resumed["snapshot_sequence"],
                    resumed["replayed"], report.seconds, "; ".join(report.problems) or "intact",
                    ", ".join(sorted(core.teams)))
    first = max(report.last_sequence + 1, since)
    return core, JournalWriter(state, first_sequence=first), resumed
