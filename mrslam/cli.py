"""The ``mrslam`` command. Each subcommand parses its arguments and calls a ``run`` function.

Heavy imports (gtsam, open3d, zenoh) happen inside the commands, so ``mrslam --help`` is fast
and ``mrslam agent`` never loads the server's libraries.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from typer.core import TyperCommand, TyperGroup, TyperOption

from mrslam import __version__


class _PlainFlags:
    """``--help`` shows no ``<bool>`` after a flag (``--help``, ``--version``, ``--merge``)
    and no ``<int>`` after ``-v``: they take no value."""

    def get_params(self, ctx: Any) -> list[Any]:
        params: list[Any] = super().get_params(ctx)  # type: ignore[misc]
        for p in params:
            if isinstance(p, TyperOption) and (p.is_flag or p.count) and p.metavar is None:
                p.metavar = ""
        return params


class PlainFlagsCommand(_PlainFlags, TyperCommand):
    pass


class PlainFlagsGroup(_PlainFlags, TyperGroup):
    pass


app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode="markdown",
                  cls=PlainFlagsGroup,
                  help="Multi-robot active SLAM: server, robot agent, simulator and tools.")
log = logging.getLogger("mrslam")

ConfigOpt = Annotated[Path | None, typer.Option("--config", "-c", help="YAML config file")]
VerboseOpt = Annotated[int, typer.Option(
    "--verbose", "-v", count=True,
    help="more logging, repeatable: -v INFO, -vv DEBUG (server, agent, sim: INFO without it)")]


#: the daemons log INFO without -v; the tools WARNING
DAEMONS = ("server", "agent", "sim")
PLAIN_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)-7s %(name)s%(robot)s: %(message)s"
PLAIN_DATE = "%Y-%m-%d %H:%M:%S"


class RobotTag(logging.Filter):
    """Puts `` [ID]`` into each record's ``robot`` field: the robot a line is about (a record
    logged with ``extra={"robot_id": ...}``), else the process's own robot (an agent's)."""

    def __init__(self, robot_id: str | None = None) -> None:
        super().__init__()
        self.robot_id = robot_id

    def filter(self, record: logging.LogRecord) -> bool:
        rid = getattr(record, "robot_id", None) or self.robot_id
        record.robot = f" [{rid}]" if rid else ""
        return True


class PlainFormatter(logging.Formatter):
    """One dated line per line of text: a message or traceback of several lines repeats the
    date, level and logger on each, so a log file never has a line without a date."""

    def __init__(self) -> None:
        super().__init__(PLAIN_FORMAT, PLAIN_DATE)

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        if "\n" not in text:
            return text
        first, *rest = text.split("\n")
        prefix = first[:len(first) - len(record.message.split("\n", 1)[0])]
        return "\n".join([first, *(prefix + line for line in rest if line.strip())])


def log_level(command: str, verbose: int) -> int:
    """The daemons: INFO, -vv DEBUG (the demo starts the server with -v). Tools: WARNING,
    -v INFO, -vv DEBUG."""
    if command in DAEMONS:
        return logging.DEBUG if verbose >= 2 else logging.INFO
    return logging.WARNING - 10 * min(verbose, 2)


def setup_logging(verbose: int, command: str = "", robot_id: str | None = None,
                  terminal: bool | None = None) -> RobotTag:
    """Configure the root logger once per process: Rich on a terminal, else plain dated lines
    that never wrap (a daemon's log file). Returns the filter that tags the process's robot.

    Log lines go to standard error, beside a command's one-line failure (``_fail``): standard
    output is for a command's data (a benchmark's JSON, ``config``'s YAML), which a log line
    must never break when it is redirected to a file."""
    import sys

    if terminal is None:
        terminal = sys.stderr.isatty()
    handler: logging.Handler
    if terminal:
        from rich.console import Console
        from rich.logging import RichHandler

        handler = RichHandler(console=Console(stderr=True), show_path=False,
                              rich_tracebacks=False)
        handler.setFormatter(logging.Formatter("%(name)s%(robot)s: %(message)s", "[%X]"))
    else:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(PlainFormatter())
    tag = RobotTag(robot_id)
    handler.addFilter(tag)
    handler.set_name("mrslam")
    root = logging.getLogger()
    for old in [h for h in root.handlers if h.get_name() == "mrslam"]:
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(log_level(command, verbose))
    return tag


def _fail(text: str, code: int = 2) -> NoReturn:
    typer.echo(f"mrslam: {' '.join(text.split())}", err=True)   # one line, always
    raise typer.Exit(code)


def _os_problem(e: OSError) -> str:
    """``path: what`` for a failed file operation, without Python's ``[Errno n]``."""
    what = e.strerror or str(e)
    return f"{e.filename}: {what}" if e.filename else what


def call(command: str, fn: Callable[[], Any]) -> Any:
    """Run a command body; expected failures become one line on stderr and exit code 2."""
    import pydantic

    from schemas.bus import BusError
    from schemas.config_loading import ConfigError, describe
    from schemas.errors import SchemaError

    try:
        return fn()
    except NotImplementedError:
        _fail(f"{command}: not implemented yet")
    except (ConfigError, BusError, SchemaError) as e:
        _fail(f"{command}: {e}")
    except pydantic.ValidationError as e:   # a model built outside the config loader
        _fail(f"{command}: config error: {describe(e)}")
    except OSError as e:   # a folder that is a file, a full disk, no permission...
        _fail(f"{command}: {_os_problem(e)}")
    except KeyboardInterrupt:
        _fail(f"{command}: interrupted", 130)
    except Exception as e:
        if getattr(e, "user_error", False):  # typed errors of our packages about bad input
            _fail(f"{command}: {e}")
        raise


def check_out(command: str, path: Path, *, folder: bool = True) -> None:
    """Fail at once, in one line, when ``--out`` cannot be written: a file on the way (e.g.
    ``/etc/passwd/x``), a file where a folder goes or the other way round, no permission."""
    if folder and path.exists() and not path.is_dir():
        _fail(f"{command}: --out {path}: exists and is not a folder")
    if not folder and path.is_dir():
        _fail(f"{command}: --out {path}: is a folder; give a file name")
    start = path if folder else path.parent
    for parent in (start, *start.parents):
        if parent.exists():
            if not parent.is_dir():
                _fail(f"{command}: --out {path}: {parent} is a file, not a folder")
            if not os.access(parent, os.W_OK | os.X_OK):
                _fail(f"{command}: --out {path}: cannot write in {parent}")
            return


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mrslam {__version__}")
        raise typer.Exit(0)


@app.callback()
def main_callback(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="print the version and exit")] = False,
) -> None:
    """mrslam command line."""


FoxgloveOpt = Annotated[int | None, typer.Option(
    "--foxglove", metavar="PORT", min=0, max=65535, help="serve the Foxglove channels live "
    "over a WebSocket on this loopback port (0: any free one), for Foxglove to connect to")]


ConsoleOpt = Annotated[int | None, typer.Option(
    "--console", metavar="PORT", min=0, max=65535, help="serve the operator console (a web "
    "page with the maps, the robots and fleet controls) on this loopback port (0: any free "
    "one); its address with the token is printed at start (docs/console.md)")]


MapOpt = Annotated[Path | None, typer.Option(
    "--map", help="start on a previous mission's map: its run folder, its server's folder, "
    "its state folder or a known_map folder (known_map.path; docs/known-map.md)")]
MapModeOpt = Annotated[str | None, typer.Option(
    "--map-mode", help="with --map: localize (the map stays as it is; the default) or "
    "extend (what the robots see is mapped into it) (known_map.mode)")]


def _map_check(command: str, path: Path | None) -> None:
    """Refuse a ``--map`` that is no folder at once, in one line (what is in the folder is
    checked when the map is read)."""
    if path is not None and not path.is_dir():
        _fail(f"{command}: --map {path}: {'not a folder' if path.exists() else 'no such folder'}"
              " (a run folder, a state folder or a known_map folder is)")


@app.command()
def server(
    config: ConfigOpt = None,
    insecure: Annotated[bool, typer.Option(
        "--insecure", help="allow listening beyond this machine without TLS and access rules "
        "(bus.insecure_listen; warned at every start)")] = False,
    map_path: MapOpt = None,
    map_mode: MapModeOpt = None,
    foxglove: FoxgloveOpt = None,
    console: ConsoleOpt = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Run the central server daemon (Zenoh router, SLAM, merging, exploration)."""
    setup_logging(verbose, "server")
    _map_check("server", map_path)

    def body() -> Any:
        from server.runtime.daemon import run

        overrides: dict[str, Any] = {"bus": {"insecure_listen": True}} if insecure else {}
        known = {k: v for k, v in (("path", str(map_path) if map_path else None),
                                   ("mode", map_mode)) if v is not None}
        if known:
            overrides["known_map"] = known
        return run(config, overrides or None,
                   foxglove_port=foxglove, console_port=console,
                   on_console=lambda c: typer.echo(f"console: {c.url}", err=True))

    call("server", body)


@app.command()
def agent(
    config: ConfigOpt = None,
    robot_id: Annotated[str | None, typer.Option("--robot-id", help="robot id, e.g. r1")] = None,
    connect: Annotated[list[str] | None, typer.Option(
        help="router endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)")] = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Run the robot agent (hardware drivers or the simulator backend)."""
    tag = setup_logging(verbose, "agent", robot_id)
    overrides: dict[str, Any] = {}
    if robot_id is not None:
        overrides["robot_id"] = robot_id
    if connect:
        overrides["bus"] = {"connect": list(connect)}

    def body() -> Any:
        from robot_agent.config import AgentConfig
        from robot_agent.runtime import run
        from schemas.config_loading import load_config

        if tag.robot_id is None:   # every line of the agent's log names its robot
            tag.robot_id = load_config(AgentConfig, config, overrides).robot_id
        return run(config, overrides)

    call("agent", body)


@app.command()
def sim(
    config: ConfigOpt = None,
    scenario: Annotated[str | None, typer.Option(help="scenario, e.g. small-house-3")] = None,
    world: Annotated[Path | None, typer.Option(help="world file (.world/.sdf/nav2 .yaml)")] = None,
    robot: Annotated[list[str] | None, typer.Option(
        help="robot spawn ID:X,Y[,YAW][:SENSOR]: metres, yaw in radians, sensor lidar "
        "(default), depth (a depth camera on a turning tower) or depth-fixed (repeatable); "
        "replaces the scenario's robots")] = None,
    seed: Annotated[int | None, typer.Option(help="random seed")] = None,
    lockstep: Annotated[bool | None, typer.Option(
        "--lockstep/--real-time", help="wait for every agent each step, or run in real time")
    ] = None,
    rtf: Annotated[float | None, typer.Option(help="real-time factor, e.g. 5")] = None,
    duration: Annotated[float | None, typer.Option(help="stop after this simulated time [s]")
                        ] = None,
    out: Annotated[Path | None, typer.Option(help="folder for truth.jsonl and summary.json")
                   ] = None,
    connect: Annotated[list[str] | None, typer.Option(
        help="router endpoint to connect to (repeatable)")] = None,
    listen: Annotated[list[str] | None, typer.Option(
        help="run standalone: open a router listening here, e.g. tcp/127.0.0.1:7447")] = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Run the 2D multi-robot simulator as its own process."""
    setup_logging(verbose, "sim")
    if out is not None:
        check_out("sim", out)

    def body() -> Any:
        from sim.config import parse_robot_args
        from sim.process import run

        overrides: dict[str, Any] = {}
        for key, value in (("scenario", scenario), ("seed", seed), ("lockstep", lockstep),
                           ("real_time_factor", rtf), ("duration_s", duration)):
            if value is not None:
                overrides[key] = value
        if world is not None:
            overrides["world"] = str(world)
        if out is not None:
            overrides["out"] = str(out)
        if robot:
            overrides["robots"], overrides["sensors"] = parse_robot_args(robot)
        bus: dict[str, Any] = {}
        if listen:
            bus.update(mode="router", listen=list(listen), connect=list(connect or []))
        elif connect:
            bus["connect"] = list(connect)
        if bus:
            overrides["bus"] = bus
        summary = run(config, overrides)
        typer.echo(f"simulated {summary['sim_time_s']:.1f} s in {summary['steps']} steps "
                   f"({summary['wall_s']:.1f} s wall)", err=True)
        return summary

    call("sim", body)


@app.command()
def demo(
    config: ConfigOpt = None,
    scenario: Annotated[str | None, typer.Option(
        help="scenario of scenarios.yaml (default small-house-3 unless --world is given)")] = None,
    world: Annotated[Path | None, typer.Option(help="world file instead of a scenario")] = None,
    robot: Annotated[list[str] | None, typer.Option(
        help="robot spawn ID:X,Y[,YAW][:SENSOR]: metres, yaw in radians, sensor lidar "
        "(default), depth (a depth camera on a turning tower) or depth-fixed (repeatable)"
        )] = None,
    area: Annotated[float | None, typer.Option(
        help="area to cover [m²]: free space plus the wall faces bounding it; default: the "
        "world's")] = None,
    coverage: Annotated[float | None, typer.Option(help="coverage threshold (0..1]")] = None,
    seed: Annotated[int | None, typer.Option(help="random seed (default 0)")] = None,
    lockstep: Annotated[bool | None, typer.Option(
        "--lockstep/--real-time", help="deterministic lockstep (the default), or real time × "
        "--rtf")] = None,
    rtf: Annotated[float | None, typer.Option(
        help="real-time factor with --real-time (default 5)")] = None,
    explorer: Annotated[str | None, typer.Option(
        help="voronoi (the default) or frontier")] = None,
    max_sim_time: Annotated[float | None, typer.Option(
        help="give up after this sim time [s] (default 3600)")] = None,
    spurious_detections: Annotated[float | None, typer.Option(
        help="share of tag views drawn false by the simulator (0..1, default 0)")] = None,
    coordination: Annotated[str | None, typer.Option(
        help="team targets: joint (the default: the free robots assigned together on path "
        "costs) or greedy (each takes its cheapest target away from the others'; the "
        "dissertation's rule)")] = None,
    merge: Annotated[bool | None, typer.Option(
        "--merge/--no-merge", help="merge maps at rendezvous (the default)")] = None,
    known_starts: Annotated[bool | None, typer.Option(
        "--known-starts/--unknown-starts", help="give the server the robots' start poses: one "
        "team from the start (default: unknown)")] = None,
    record: Annotated[bool | None, typer.Option(
        "--record/--no-record", help="record the run into run.mcap (the default)")] = None,
    foxglove: FoxgloveOpt = None,
    console: ConsoleOpt = None,
    server_restarts: Annotated[int | None, typer.Option(
        help="restart a server that dies at most this many times (0: never; default 5)")
    ] = None,
    map_path: MapOpt = None,
    map_mode: MapModeOpt = None,
    out: Annotated[Path | None, typer.Option(help="run folder")] = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Start server, simulator and agents on loopback and explore a scenario or world. The
    options given replace the config file's keys (`mrslam config demo` lists them all)."""
    setup_logging(verbose, "demo")
    if out is not None:
        check_out("demo", out)
    _map_check("demo", map_path)

    def body() -> Any:
        from mrslam.demo import run
        from sim.config import parse_robot_args

        given = {"scenario": scenario, "world": str(world) if world else None,
                 "area_m2": area, "coverage": coverage, "seed": seed, "lockstep": lockstep,
                 "rtf": rtf, "explorer": explorer, "max_sim_time_s": max_sim_time,
                 "spurious_detections": spurious_detections, "coordination": coordination,
                 "merge": merge, "known_starts": known_starts, "record": record,
                 "server_restarts": server_restarts, "out": str(out) if out else None,
                 "map": str(map_path) if map_path else None, "map_mode": map_mode}
        opts: dict[str, Any] = {k: v for k, v in given.items() if v is not None}
        if robot:
            opts["robots"], opts["sensors"] = parse_robot_args(robot)
        report = run(opts, foxglove_port=foxglove, console_port=console, config=config)
        if report.get("stopped_by"):   # as a shell reports a command a signal ended
            import signal

            _fail(f"demo: stopped by {report['stopped_by']}; the report of the run so far "
                  "is in its folder", 128 + signal.Signals[report["stopped_by"]].value)
        if not report["reached"]:
            raise typer.Exit(1)
        return report

    call("demo", body)


ConnectOpt = Annotated[list[str] | None, typer.Option(
    "--connect", help="router endpoint to connect to (repeatable; default tcp/127.0.0.1:7447)")]
ListenOpt = Annotated[list[str] | None, typer.Option(
    "--listen", help="run standalone: open a router listening here (repeatable)")]
ZenohConfigOpt = Annotated[Path | None, typer.Option(
    "--zenoh-config", help="Zenoh json5 config (TLS, access control)")]


def _bus_config(connect: list[str] | None, listen: list[str] | None,
                zenoh_config: Path | None) -> Any:
    from schemas.bus import zenoh_config as read_zenoh_config
    from schemas.config import BusConfig
    from schemas.config_loading import validate

    if zenoh_config is not None:   # named on the command line: read before anything else
        read_zenoh_config("client", config_file=str(zenoh_config))
    fields: dict[str, Any] = {"zenoh_config": str(zenoh_config) if zenoh_config else None}
    if listen:
        fields.update(mode="router", listen=list(listen), connect=list(connect or []))
    elif connect:
        fields["connect"] = list(connect)
    return validate(BusConfig, fields, root="bus")


@app.command()
def record(
    out: Annotated[Path, typer.Option(help="MCAP file to write, e.g. run.mcap")],
    foxglove_channels: Annotated[bool, typer.Option(
        "--foxglove-channels/--wire-only", help="also write the Foxglove channels (scans, "
        "maps, frames, trajectories, events) beside the wire messages")] = True,
    foxglove: FoxgloveOpt = None,
    compression: Annotated[str, typer.Option(help="chunk compression: zstd, lz4 or none")
                           ] = "zstd",
    duration: Annotated[float | None, typer.Option(help="stop after this many seconds")] = None,
    exclude: Annotated[list[str] | None, typer.Option(
        help="leave out keys matching this key expression (repeatable), "
             "e.g. 'mrslam/sim/robot/*/image'")] = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    zenoh_config: ZenohConfigOpt = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Record every message under mrslam/** into an MCAP file until interrupted."""
    setup_logging(verbose, "record")
    check_out("record", out, folder=False)
    if compression not in ("zstd", "lz4", "none"):
        _fail(f"record: unknown compression {compression!r} (zstd, lz4 or none)")

    def body() -> Any:
        from recording.record import run

        summary = run(out, _bus_config(connect, listen, zenoh_config),
                      foxglove=foxglove_channels, foxglove_port=foxglove,
                      compression=compression, duration_s=duration,  # type: ignore[arg-type]
                      exclude=tuple(exclude or ()))
        typer.echo(f"recorded {summary['messages']} messages on {summary['keys']} keys "
                   f"({summary['undecodable']} undecodable) into {out}", err=True)
        return summary

    call("record", body)


@app.command()
def replay(
    recording: Annotated[Path, typer.Argument(help="MCAP file written by mrslam record")],
    speed: Annotated[float, typer.Option(
        min=0.0, help="time scale: 2 = twice as fast, 0 = as fast as possible")] = 1.0,
    only: Annotated[list[str] | None, typer.Option(
        help="replay only keys matching this key expression, e.g. 'mrslam/robot/**' "
             "(repeatable)")] = None,
    until_ns: Annotated[int | None, typer.Option(
        help="stop after the messages stamped at this time [ns]")] = None,
    max_gap: Annotated[float, typer.Option(
        min=0.0, help="shorten longer pauses of the recording to this [s]")] = 5.0,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    zenoh_config: ZenohConfigOpt = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Publish a recording onto the bus again with its timing (e.g. to run a new server on it)."""
    setup_logging(verbose, "replay")

    def body() -> Any:
        from recording.replay import run

        summary = run(recording, _bus_config(connect, listen, zenoh_config), speed=speed,
                      only=list(only or []), until_ns=until_ns, max_gap_s=max_gap)
        typer.echo(f"replayed {summary['published']} of {summary['recorded']} messages in "
                   f"{summary['wall_s']:.1f} s ({summary['unreadable']} unreadable)", err=True)
        return summary

    call("replay", body)


@app.command()
def merge(
    first: Annotated[Path, typer.Argument(help="first session (MCAP)")],
    second: Annotated[Path, typer.Argument(help="second session (MCAP)")],
    out: Annotated[Path, typer.Option(help="output folder")],
    marker: Annotated[str | None, typer.Option(
        help="pose X,Y,YAW of the second session's marker as measured in the first: "
        "metres, yaw in radians")] = None,
    config: ConfigOpt = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Merge the maps of two recorded sessions offline."""
    setup_logging(verbose, "merge")
    check_out("merge", out)

    def body() -> Any:
        from schemas.config_loading import load_config
        from server.config import ServerConfig
        from server.offline.offline_merge import run_merge

        cfg = load_config(ServerConfig, config)
        rep = run_merge(first, second, out, marker, cfg)
        typer.echo(f"merged: transform {rep['transform']}, {rep['sightings_used']} sightings, "
                   f"{rep['map_matches']} map matches; report in {out / 'merge_report.json'}")
        return rep

    call("merge", body)


@app.command("slam-log")
def slam_log(
    log_file: Annotated[Path, typer.Argument(
        help="CARMEN log (.clf/.log, optionally .gz/.bz2), ROS 1 bag (.bag) or ROS 2 bag "
        "folder: a LaserScan or MultiEchoLaserScan topic, with odometry (an Odometry topic or "
        "/tf) or without (then from scan matching)")],
    out: Annotated[Path, typer.Option(help="output folder")],
    scan_topic: Annotated[str | None, typer.Option(
        help="a bag's scan topic (default: the one with the most messages)")] = None,
    odom_topic: Annotated[str | None, typer.Option(
        help="a bag's Odometry topic (default: the one with the most messages; without one, "
        "/tf; without that, scan matching)")] = None,
    echo: Annotated[str | None, typer.Option(
        metavar="first|last", help="the echo of a MultiEchoLaserScan beam (default: first)")
    ] = None,
    laser_pose: Annotated[str | None, typer.Option(
        metavar="X,Y,YAW", help="the laser's pose on the robot [m, m, rad] where the bag has "
        "no static transform for it (replaces /tf_static's)")] = None,
    odometry: Annotated[str | None, typer.Option(
        metavar="auto|laser|odom|scans", help="odometry source; scans: from scan matching, "
        "ignoring the recording's (default: auto)")] = None,
    config: ConfigOpt = None,
    verbose: VerboseOpt = 0,
) -> None:
    """Run per-robot graph SLAM offline on a CARMEN laser log or a ROS bag."""
    setup_logging(verbose, "slam-log")
    check_out("slam-log", out)
    pose: tuple[float, ...] | None = None
    if laser_pose is not None:
        try:
            pose = tuple(float(v) for v in laser_pose.split(","))
        except ValueError:
            pose = ()
        if len(pose) != 3:
            _fail(f"slam-log: --laser-pose {laser_pose!r}: give X,Y,YAW (metres, radians)")

    def body() -> Any:
        from server.offline.slam_log import run

        return run(log_file, out, config, scan_topic, odom_topic, echo=echo, laser_pose=pose,
                   odometry=odometry)

    call("slam-log", body)


@app.command("export")
def export(
    source: Annotated[Path, typer.Argument(
        help="a recording (run.mcap) or a CARMEN log (.clf/.log, optionally .gz/.bz2)")],
    ros2: Annotated[Path, typer.Option(
        "--ros2", help="ROS 2 bag folder to write (rosbag2, MCAP storage; must not exist)")],
    verbose: VerboseOpt = 0,
) -> None:
    """Write a recording or a CARMEN log as a ROS 2 bag: LaserScan, OccupancyGrid, TF, Path
    (docs/ros2.md)."""
    setup_logging(verbose, "export")
    if ros2.exists():
        _fail(f"export: --ros2 {ros2}: exists already; give a new folder")
    check_out("export", ros2.parent)

    def body() -> Any:
        from mrslam import ros2 as bags

        if source.suffix == ".mcap":
            summary = bags.export_recording(source, ros2)
        else:
            summary = bags.export_carmen(source, ros2)
        typer.echo(f"wrote {summary['messages']} messages on {len(summary['topics'])} topics "
                   f"into {ros2}", err=True)
        return summary

    call("export", body)


@app.command("eval-relations")
def eval_relations(
    poses: Annotated[Path, typer.Argument(help="poses.txt: timestamp x y theta per line")],
    relations: Annotated[Path, typer.Argument(help="relations file: t1 t2 x y z roll pitch yaw")],
    tolerance: Annotated[float, typer.Option(help="max stamp difference when matching [s]")
                         ] = 0.005,
    json_out: Annotated[bool, typer.Option("--json", help="print one JSON line")] = False,
) -> None:
    """Score poses against reference relations (Kümmerle et al. 2009): mean ± std of the
    translational [m] and rotational [deg] relation errors."""

    def body() -> Any:
        from server.offline.evaluation import run

        return run(poses, relations, tolerance_s=tolerance, as_json=json_out)

    call("eval-relations", body)


@app.command("lidar-dump")
def lidar_dump(
    port: Annotated[str, typer.Option(help="serial port, e.g. /dev/ttyUSB0 or /dev/rplidar")],
    scans: Annotated[int, typer.Option(min=1, help="number of sweeps to print")] = 1,
    baud: Annotated[int, typer.Option(help="baud rate (A2: 115200, A3: 256000)")] = 115200,
    beams: Annotated[int, typer.Option(min=8, max=8192, help="beams per sweep")] = 360,
    timeout: Annotated[float, typer.Option(help="give up after this long without a sweep [s]")
                       ] = 10.0,
    verbose: VerboseOpt = 0,
) -> None:
    """Print sweeps of an RPLIDAR: `stamp_ns n angle_0 range_0 ...` (rad, m, no return = inf)."""
    setup_logging(verbose, "lidar-dump")
    if not verbose:   # its failure line names the device's last problem; once is enough
        logging.getLogger("robot_agent.drivers.rplidar").setLevel(logging.ERROR)

    def body() -> Any:
        from robot_agent.lidar_dump import run

        return run(port, scans, baud, beams, timeout)

    call("lidar-dump", body)


@app.command("world-map")
def world_map(
    world: Annotated[Path, typer.Argument(help="Gazebo .world/.sdf file or nav2 map .yaml")],
    out: Annotated[Path, typer.Option(help="output folder")],
    resolution: Annotated[float, typer.Option(help="cell size [m]")] = 0.05,
) -> None:
    """Write a world's ground-truth occupancy map (nav2 format) and its free area."""
    if not 0.0 < resolution < float("inf"):   # NaN fails too
        _fail(f"world-map: --resolution must be a positive number of metres, got {resolution}")
    check_out("world-map", out)

    def body() -> Any:
        from sim.world_map import run

        fig = run(world, resolution, out)
        typer.echo(f"free area {fig['free_area_m2']:.2f} m², with wall faces "
                   f"{fig['explorable_area_m2']:.2f} m² (largest region "
                   f"{fig['largest_region_m2']:.2f} m², bounding box {fig['bbox_m2']:.2f} m²) "
                   f"-> {fig['map']}")
        return fig

    call("world-map", body)


@app.command("config")
def config_defaults(
    component: Annotated[str | None, typer.Argument(
        help="server, agent, sim or demo (with --markdown: all of them when left out)")] = None,
    markdown: Annotated[bool, typer.Option(
        "--markdown", help="print the reference instead: every key's type, default and "
        "meaning (what docs/config.md holds)")] = False,
) -> None:
    """Print a component's default configuration as YAML, a starting point for `-c FILE`."""

    def body() -> Any:
        from mrslam import configdoc

        if markdown:
            text = (configdoc.render_component(component) if component
                    else configdoc.render_reference())
        elif component is None:
            _fail(f"config: name a component: {', '.join(configdoc.COMPONENTS)}")
        else:
            text = configdoc.default_yaml(component)
        typer.echo(text, nl=False)

    call("config", body)


for _info in app.registered_commands:   # every command, including those added above
    if _info.cls in (None, TyperCommand):
        _info.cls = PlainFlagsCommand


def main() -> None:
    """The ``mrslam`` entry point: like Typer's own, but a usage error (an unknown option, a
    value that does not parse) is one line on stderr, exit code 2, as every expected failure."""
    import sys

    try:
        code = app(prog_name="mrslam", standalone_mode=False)
    except typer.TyperException as e:
        if type(e).__name__ == "NoArgsIsHelpError":   # Typer printed the help already
            sys.exit(e.exit_code)
        ctx = getattr(e, "ctx", None)
        where = f"{ctx.info_name}: " if ctx is not None and ctx.parent is not None else ""
        typer.echo(f"mrslam: {where}{' '.join(e.format_message().split())}", err=True)
        sys.exit(e.exit_code)
    except typer.Abort:
        typer.echo("mrslam: aborted", err=True)
        sys.exit(1)
    sys.exit(code if isinstance(code, int) else 0)

if __name__ == "__main__":
    main()
