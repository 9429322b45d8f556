"""``mrslam demo``: explore a simulated world with the real processes on loopback.

The server (Zenoh router, SLAM, exploration, control), the simulator and one agent per robot run
as separate processes, exactly as they would on a robot team; this module only starts them,
watches the bus for progress, stops them, and scores the run against the simulator's ground
truth into a run folder (resolved config, ``report.json``, maps, trajectories, figures).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml
from pydantic import Field, model_validator

from mrslam.console_shot import ConsoleShot
from mrslam.launch import GroupClosed, Proc, ProcessGroup
from mrslam.reboots import Reboots
from mrslam.supervise import Exit, RestartPolicy, Supervisor
from schemas.config import ConfigModel, Coordination, Finite
from schemas.config_loading import ConfigError, load_config, write_resolved
from schemas.stopping import SignalStop
from server.knownmap.config import MapMode
from sim.config import SensorKind
from sim.loader import site_of

if TYPE_CHECKING:
    from mrslam.monitor import Monitor

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]

#: after a stop signal (SIGTERM, SIGINT, SIGHUP) the run's processes are asked to stop at
#: once, and what is still running this long later is killed [s]; a second signal kills at
#: once. The report follows, without the figures (nothing of the run left 5 s after it).
KILL_AFTER_S = 3.5


class DemoConfig(ConfigModel):
    """Everything a demo run is made of; saved as ``demo_config.yaml`` in the run folder."""

    scenario: str | None = Field(
        "small-house-3", description="a case of scenarios_file: world, robots, area, threshold and "
        "controller settings")
    scenarios_file: str | None = Field(
        None, description="where the scenario is defined; default: the cases that ship with "
        "mrslam (sim/worlds/scenarios.yaml)")
    world: str | None = Field(
        None, description="a world file (.world/.sdf or nav2 .yaml) instead of the scenario's")
    robots: dict[str, Pose] = Field(
        default_factory=dict, description="robot id -> spawn pose [x, y, yaw]; replaces the "
        "scenario's robots")
    sensors: dict[str, SensorKind] = Field(
        default_factory=dict, description="robot id -> range sensor (lidar, depth, "
        "depth-fixed); replaces the scenario's for that robot; default lidar")
    area_m2: float | None = Field(
        None, gt=0, description="area to cover (free space and the wall faces bounding it, "
        "as coverage counts both); default: the world's, from its geometry")
    coverage: float | None = Field(None, gt=0, le=1, description="default: the scenario's")
    seed: int = Field(0, description="the simulator's random seed")
    lockstep: bool = Field(
        True, description="the simulator waits for every agent each step (deterministic); false: "
        "real time × rtf")
    rtf: float = Field(5.0, gt=0, description="real-time factor when not in lockstep")
    explorer: Literal["voronoi", "frontier"] = Field(
        "voronoi", description="voronoi or frontier (the server's explore.explorer)")
    cells_per_m: float | None = Field(None, gt=0, description="default: the scenario's, else 15")
    # λ of the Voronoi explorer; default 0.5, not the scenario's: the dissertation's λ = 0 for
    # the large world (cost = distance from the start only) sends a robot to and fro across the
    # map; pass the scenario's value to reproduce it
    lam: float | None = Field(
        None, ge=0, le=1, description="λ once all robots are in one team (explore.lam); default "
        "0.5, not the scenario's")
    v_mps: float | None = Field(
        None, description="forward speed; default: the scenario's, else 0.3")
    omega_max_rps: float | None = Field(
        None, description="largest turn rate; default: the scenario's, else 1.5")
    lookahead_m: float | None = Field(
        None, description="pure pursuit look-ahead; default: the scenario's, else 1.0")
    spurious_detections: float = Field(0.0, ge=0, le=1, description="share of tag views "
                                       "the simulator draws false (merge verification test)")
    coordination: Coordination = Field(
        "joint", description="team targets: joint or greedy (the server's teams.coordination)")
    merge: bool = Field(True, description="False: robots never merge their maps")
    known_starts: bool = Field(False, description="tell the server where the robots start: "
                               "one team from the first scan (no rendezvous needed)")
    record: bool = Field(True, description="record every bus message into <out>/run.mcap")
    clock_steps: dict[str, list[tuple[Finite, Finite]]] = Field(
        default_factory=dict, description="robots whose own clocks step: {r2: [[at_s, "
        "step_s]]} (sim time, step), to try the server's clock handling")
    reboot: dict[str, Finite] = Field(
        default_factory=dict, description="robots that reboot mid-run: {r2: at_s}: once the "
        "simulation passes at_s [s] the robot's agent is killed (SIGKILL) and, reboot_s later, "
        "started again with its odometry back at zero (agent sim_odometry_at_zero)")
    reboot_s: float = Field(
        3.0, gt=0, description="wall-clock time a rebooting agent stays down (the robot stands "
        "meanwhile; the others go on)")
    max_sim_time_s: float = Field(
        3600.0, gt=0, description="the simulator stops after this much simulated time")
    wall_timeout_s: float = Field(
        1800.0, gt=0, description="the demo gives up after this much wall-clock time")
    server_restarts: int = Field(
        5, ge=0, description="a server that dies (killed, crashed) is started again with the "
        "same config, at most this many times in a run (0: never); it resumes from its "
        "journal in the run folder while the simulator and agents go on")
    restart_back_off_s: float = Field(
        1.0, gt=0, description="the wait before the first restart; each next one waits twice "
        "as long (at most 30 s)")
    map: str | None = Field(
        None, description="start on a previous mission's map: its run folder, state folder or "
        "known_map folder (docs/known-map.md); the robots are not told where they are")
    map_mode: MapMode = Field(
        "localize", description="with map: localize (the map stays as it is) or extend (what "
        "the robots see is mapped into it)")
    out: str = Field("", description="the run folder; empty: runs/<scenario>-<date>-<time>")
    endpoint: str | None = Field(
        None, description="where the server listens (tcp/127.0.0.1:PORT); default: a free "
        "loopback port")
    agent_connect: dict[str, str] = Field(
        default_factory=dict, description="robots whose agent connects elsewhere than the "
        "server's endpoint: {r2: tcp/127.0.0.1:PORT} (a relay in front of the server, to try "
        "a slow or bursty link)")

    @model_validator(mode="before")
    @classmethod
    def _world_without_scenario(cls, data: Any) -> Any:
        """A world given without a scenario is run without one (not with the default
        scenario's robots and settings)."""
        if isinstance(data, dict) and data.get("world") and "scenario" not in data:
            return {**data, "scenario": None}
        return data


def previous_run(out: Path) -> str | None:
    """What of an earlier run ``out`` holds (its server's state, its report), or None. A
    demo started there would have its server resume the old state (as after a crash, when
    the demo restarts it) while the simulation starts again from nothing: every scan is
    refused as older than the state, and the run never ends."""
    state = out / "server" / "state"
    if state.is_dir() and any(state.iterdir()):
        return f"{state} is not empty"
    if (out / "report.json").exists():
        return f"{out / 'report.json'} exists"
    return None


def run(overrides: dict[str, Any] | None = None, progress: bool = True,
        foxglove_port: int | None = None, console_port: int | None = None,
        config: str | Path | None = None) -> dict[str, Any]:
    """Run one demo; returns the report (also written to ``<out>/report.json``). ``config``:
    a YAML file of ``DemoConfig`` keys, which ``overrides`` replace key by key (a run folder's
    ``demo_config.yaml`` repeats that run given another ``out``: in its own folder the server
    would resume the old run's journal).
    ``foxglove_port``: serve the run live to Foxglove on that loopback port (the recorder
    serves it, else the server). ``console_port``: the server serves the operator console
    there (0: a free port); its address is printed, and a screenshot of the page at the end
    goes to ``<out>/console.png``."""
    from rich.console import Console

    cfg = load_config(DemoConfig, config, overrides or {}, environ={})  # bad: ConfigError
    if not cfg.out:
        name = cfg.scenario or Path(cfg.world or "world").stem
        cfg.out = str(Path("runs") / time.strftime(f"{name}-%Y%m%d-%H%M%S"))
    out = Path(cfg.out)
    if (held := previous_run(out)) is not None:
        raise ConfigError(f"out: {out} already holds a run ({held}): its server would resume "
                          "that run's state under a new simulation; give another folder, or "
                          "remove this one")
    console = Console(stderr=True)
    with SignalStop(name="mrslam demo") as stopping:
        plan = plan_run(cfg)
        for name, ids in (("clock_steps", cfg.clock_steps), ("reboot", cfg.reboot),
                      ("agent_connect", cfg.agent_connect)):
            if unknown := sorted(set(ids) - set(plan["robots"])):
                raise ConfigError(f"{name}: no robot {', '.join(unknown)} in this run")
        write_resolved(cfg, out, "demo_config.yaml")
        if cfg.map:
            plan["map"], plan["map_frame"] = _start_map(cfg.map, plan, out)
        console.print(f"[bold]mrslam demo[/]: {plan['title']} — {len(plan['robots'])} "
                      f"robot(s), threshold {plan['threshold']:.0%} of "
                      f"{plan['area_m2']:.1f} m², "
                      f"{'lockstep' if cfg.lockstep else f'×{cfg.rtf} real time'}; "
                      f"run folder {out}")
        t0 = time.monotonic()
        watch = _execute(cfg, plan, out, console, progress, t0, stopping, foxglove_port,
                         console_port)
        from mrslam.report import build_report

        report = build_report(cfg, plan, out, watch, wall_time_s=time.monotonic() - t0,
                              figures=stopping.signum is None)
        if stopping.signum is not None:
            report["stopped_by"] = stopping.signal_name
        if cfg.reboot:
            report["agent_reboots"] = watch.get("agent_reboots", [])
        (out / "report.json").write_text(json.dumps(report, indent=2))
    from mrslam.report import print_summary

    print_summary(report, console)
    return report


def plan_run(cfg: DemoConfig) -> dict[str, Any]:
    """Resolve the scenario: world, robots, settings, and the world's true map."""
    from sim.config import DEFAULT_SCENARIOS, SimConfig, load_scenario, resolve_scene_sensors
    from sim.world_map import world_map

    scfg = SimConfig(scenario=cfg.scenario, world=cfg.world, robots=cfg.robots,
                     sensors=cfg.sensors,
                     scenarios_file=cfg.scenarios_file or str(DEFAULT_SCENARIOS))
    world, robots, sensors = resolve_scene_sensors(scfg)
    case: dict[str, Any] = (load_scenario(Path(scfg.scenarios_file), cfg.scenario)
                            if cfg.scenario else {})
    cells = cfg.cells_per_m or float(case.get("grid_cells_per_m", 15))
    truth_grid, figures = world_map(world, 1.0 / cells)
    area = cfg.area_m2 or float(figures["explorable_area_m2"])
    return {
        "title": cfg.scenario or str(world),
        "world": str(world),
        "robots": {rid: list(p) for rid, p in robots.items()},
        "sensors": sensors,
        "resolution_m": 1.0 / cells,
        "area_m2": area,
        "nominal_area_m2": case.get("total_area_m2"),
        "world_figures": figures,
        "truth_grid": truth_grid,
        "threshold": cfg.coverage or float(case.get("coverage_threshold", 0.95)),
        "lam": cfg.lam if cfg.lam is not None else 0.5,
        "v_mps": cfg.v_mps or float(case.get("v_mps", 0.3)),
        "omega_max_rps": cfg.omega_max_rps or float(case.get("omega_max_rps", 1.5)),
        "lookahead_m": cfg.lookahead_m or float(case.get("lookahead_m", 1.0)),
        "reported": case.get("reported", {}),
    }


def _start_map(path: str, plan: dict[str, Any], out: Path
               ) -> tuple[str, list[float] | None]:
    """The map named by ``--map`` found once (``MapError`` in one line when there is none),
    and written where the server reads it: ``<out>/start_map``. With it, where the map's
    frame lies in the world, for scoring (the map's note, written by the demo that started
    on it, else where its anchor robot started in the run that made it; None: unknown)."""
    from server.runtime.mapfind import find_map
    from server.runtime.mapstore import write_map

    site = site_of(plan["world"])
    known, where = find_map(path, site)
    log.warning("known map: %d keyframes from %s", len(known), where)
    frame = _map_frame(known.notes.get(WORLD_FRAME), known.anchor, Path(path))
    if frame is not None:
        known.notes[WORLD_FRAME] = " ".join(f"{v:.6f}" for v in frame)
    folder = write_map(known, out / "start_map", site, written_by=str(path))
    return str(folder.resolve()), frame


#: a known map's note: where its frame lies in the simulated world (x y θ)
WORLD_FRAME = "world_frame"


def _map_frame(note: str | None, anchor: str, path: Path) -> list[float] | None:
    if note:
        try:
            frame = [float(v) for v in note.split()]
        except ValueError:
            frame = []
        if len(frame) == 3:
            return frame
    for folder in (path, *path.parents[:3]):
        try:
            spawn = json.loads((folder / "report.json").read_text()).get("robots_spawn", {})
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(spawn, dict) and anchor in spawn:
            return [float(v) for v in spawn[anchor]][:3]
    return None


def robot_args(plan: dict[str, Any]) -> list[str]:
    """The simulator's ``--robot ID:X,Y,YAW[:SENSOR]`` options for the plan's robots."""
    out: list[str] = []
    for rid, p in plan["robots"].items():
        kind = plan["sensors"].get(rid)
        out += ["--robot", f"{rid}:{p[0]},{p[1]},{p[2]}" + (f":{kind}" if kind else "")]
    return out


def _configs(cfg: DemoConfig, plan: dict[str, Any], out: Path, endpoint: str) -> None:
    from sim.config import SimConfig

    server = {
        "bus": {"mode": "router", "listen": [endpoint], "connect": []},
        "robots": sorted(plan["robots"]),
        "clock": {"source": "sim"},
        "slam": {"grid": {"resolution_m": plan["resolution_m"], "p_hit": 0.75, "p_miss": 0.35}},
        "explore": {"explorer": cfg.explorer, "lam": plan["lam"], "total_area_m2": plan["area_m2"],
                    "coverage_threshold": plan["threshold"]},
        "control": {"v_mps": plan["v_mps"], "omega_max_rps": plan["omega_max_rps"],
                    "lookahead_m": plan["lookahead_m"]},
        "teams": {"enabled": cfg.merge, "coordination": cfg.coordination,
                  "start_poses": ({rid: [float(v) for v in p]
                                   for rid, p in plan["robots"].items()}
                                  if cfg.known_starts else {})},
        "out": str(out / "server"),
        "exit_when_done": True,
    }
    if plan.get("map"):
        server["known_map"] = {"path": plan["map"], "site": site_of(plan["world"]),
                               "mode": cfg.map_mode}
    (out / "server.yaml").write_text(yaml.safe_dump(server, sort_keys=False))
    for rid in plan["robots"]:
        agent = {"robot_id": rid, "bus": {"connect": [cfg.agent_connect.get(rid, endpoint)],
                                          "connect_timeout_ms": 30000},
                 # the simulated robots' bodies, for the LIDAR fix of tag sightings
                 "detector": {"body_radius_m": SimConfig().drive.radius_m},
                 "sim_clock_steps": [list(step) for step in cfg.clock_steps.get(rid, [])]}
        (out / f"agent_{rid}.yaml").write_text(yaml.safe_dump(agent, sort_keys=False))
        if rid in cfg.reboot:   # how it comes back: a robot's odometry starts at boot
            (out / f"agent_{rid}_rebooted.yaml").write_text(yaml.safe_dump(
                {**agent, "sim_odometry_at_zero": True}, sort_keys=False))
    sim = {"camera": {"spurious_rate": cfg.spurious_detections}}
    (out / "sim.yaml").write_text(yaml.safe_dump(sim, sort_keys=False))


def _execute(cfg: DemoConfig, plan: dict[str, Any], out: Path, console: Any,
             progress: bool, t0: float, stopping: SignalStop,
             foxglove_port: int | None = None, console_port: int | None = None
             ) -> dict[str, Any]:
    from mrslam.monitor import Monitor, Stopped
    from schemas.bus import free_local_endpoint

    endpoint = cfg.endpoint or free_local_endpoint()
    _configs(cfg, plan, out, endpoint)
    page = ConsoleShot(console_port)
    watch: dict[str, Any] = {}
    why = "stopped"
    with ProcessGroup(out / "logs") as procs:
        # a stop signal reaches every process of the run at once, whatever this thread does
        stopping.on_signal(lambda _sig, n: procs.terminate_all(KILL_AFTER_S if n == 1 else 0.0))
        live = [] if foxglove_port is None else ["--foxglove", str(foxglove_port)]
        try:
            server = procs.start("server", "server", "-c", str(out / "server.yaml"), "-v",
                                 *([] if cfg.record else live), *page.args, env=page.env)
            with Monitor(endpoint, list(plan["robots"]), stopping.event) as mon:
                why, watch = _follow(cfg, plan, out, console, progress, t0, procs, server,
                                     mon, page, endpoint, live)
        except (GroupClosed, Stopped) as e:   # stopped before the run was under way
            log.warning("%s", e)
            procs.stop(timeout_s=KILL_AFTER_S)
        if stopping.signum is not None:
            why = f"stopped by {stopping.signal_name}"
        watch["end"] = why
        watch["exit_codes"] = {p.name: p.popen.returncode for p in procs.procs}
        failed = [p for p in procs.procs if p.popen.returncode not in (0, -15, None)]
        for p in failed:
            console.print(f"[red]{p.name} exited with {p.popen.returncode}[/]:\n{p.tail()}")
    return watch


def _follow(cfg: DemoConfig, plan: dict[str, Any], out: Path, console: Any, progress: bool,
            t0: float, procs: ProcessGroup, server: Proc, mon: Monitor, page: ConsoleShot,
            endpoint: str, live: list[str]) -> tuple[str, dict[str, Any]]:
    """Start the rest of the run once the server is up, follow it to its end and stop it;
    why it ended, and what the monitor saw."""
    supervisor = Supervisor(procs, server, RestartPolicy(cfg.server_restarts,
                                                         cfg.restart_back_off_s))
    reboots: Reboots | None = None
    try:
        sim = _launch(cfg, plan, out, console, procs, server, mon, page, endpoint, live)
        threading.Thread(target=_warm_report, name="warm-report", daemon=True).start()
        reboots = Reboots(procs, mon, cfg.reboot, cfg.reboot_s, out)
        why = mon.follow(supervisor, sim, cfg.wall_timeout_s, plan["threshold"], console,
                         progress)
    except GroupClosed:
        why = "stopped"
    finally:
        if reboots is not None:
            reboots.stop()
        page.close(out / "console.png")
    if mon.stop.is_set():    # asked to stop: every process at once, killed if need be
        procs.stop(timeout_s=KILL_AFTER_S)
    else:
        procs.stop(["sim"] + [f"agent_{r}" for r in plan["robots"]])
        _let_server_come_up(supervisor, mon, timeout_s=60.0)
        procs.stop(["server"], timeout_s=60.0)
        procs.stop(["recorder"])
    watch = mon.results()
    watch["agent_reboots"] = reboots.rows if reboots is not None else []
    watch["server_restarts"] = [_restart_row(e, mon.recovery(e), t0) for e in supervisor.exits]
    return why, watch


def _warm_report() -> None:
    """Import what the report needs while the run goes on: a run stopped by a signal then
    writes its report at once (the imports alone take a second or two)."""
    try:
        import mrslam.report  # noqa: F401
        import server.runtime.outputs  # noqa: F401
    except Exception:   # the report imports them again and says what failed
        log.debug("warming the report's imports failed", exc_info=True)


def _launch(cfg: DemoConfig, plan: dict[str, Any], out: Path, console: Any,
            procs: ProcessGroup, server: Proc, mon: Monitor, page: ConsoleShot,
            endpoint: str, live: list[str]) -> Proc:
    """The recorder, the agents and the simulator, once the server is up; the simulator."""
    if not mon.wait_for_server(30.0, server.alive):
        if mon.stop.is_set():
            raise GroupClosed("stopped before the server was up")
        raise RuntimeError(f"the server did not come up:\n{server.tail()}")
    page.open(console)
    if cfg.record:  # the file appears once the recorder is on the bus
        # camera images are the simulator's business (the agents' tag detections are
        # recorded): leaving them out keeps a run's file small
        rec = procs.start("recorder", "record", "--out", str(out / "run.mcap"),
                          "--connect", endpoint, "--exclude", "mrslam/sim/robot/*/image",
                          *live)
        until = time.monotonic() + 30.0
        while rec.alive() and not (out / "run.mcap").exists() and \
                time.monotonic() < until and not mon.stop.is_set():
            time.sleep(0.1)
    for rid in plan["robots"]:
        procs.start(f"agent_{rid}", "agent", "-c", str(out / f"agent_{rid}.yaml"))
    sim_args = ["sim", "-c", str(out / "sim.yaml"), "--world", plan["world"],
                "--seed", str(cfg.seed),
                "--connect", endpoint, "--out", str(out / "sim"),
                "--duration", str(cfg.max_sim_time_s)]
    sim_args += robot_args(plan)
    sim_args += ["--lockstep"] if cfg.lockstep else ["--real-time", "--rtf", str(cfg.rtf)]
    return procs.start("sim", *sim_args)


def _let_server_come_up(supervisor: Supervisor, mon: Monitor, timeout_s: float) -> None:
    """A server restarting as the run ends gets the time to come up (replaying its journal),
    so that, stopped, it writes its outputs; one that died for good or has exited is left."""
    until = time.monotonic() + timeout_s
    while time.monotonic() < until:
        try:
            state = supervisor.poll(mon.sim_time_s)
        except GroupClosed:   # a stop signal came meanwhile
            return
        if state in ("done", "failed") or (state == "running" and mon.server_alive) or \
                mon.stop.is_set():
            return
        time.sleep(0.1)
    log.warning("the server did not come up within %.0f s of the run's end", timeout_s)


def _restart_row(e: Exit, seen: dict[str, Any], t0: float) -> dict[str, Any]:
    """One entry of ``server_restarts``: wall times in seconds since the run started."""
    return {"wall_time_s": round(e.exited_at - t0, 3),
            "sim_time_s": None if e.sim_time_s is None else round(e.sim_time_s, 2),
            "pid": e.pid, "exit_code": e.exit_code, "signal": e.signal,
            "restarted": e.restarted, "back_off_s": e.back_off_s,
            "restart_wall_time_s": (None if e.restarted_at is None
                                    else round(e.restarted_at - t0, 3)),
            "new_pid": e.new_pid, **seen}
