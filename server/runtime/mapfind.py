"""Finding the map in what a previous mission left (``mrslam server --map PATH``).

``find_map`` takes what a user names and tries, in this order:

1. ``PATH`` itself, ``PATH/known_map`` and ``PATH/server/known_map`` (a run folder's): the
   map a server writes when it stops, read as it is (``server.runtime.mapstore``);
2. ``PATH``, ``PATH/state`` and ``PATH/server/state``: a state folder, brought back as a
   resumed server would — its newest snapshot this code can read, then its journal replayed
   (an older release's state has no snapshot this code reads: its journal is replayed whole,
   as it crosses versions) — and its map taken from it: the known map's team if it had one,
   else its largest team;
3. else ``MapError`` says in one line what is there and why it is no map.

A server started on a map (``start_map``) keeps a copy of it in its state folder
(``state/known_map``): a resumed run, or a later ``find_map`` replaying the journal, starts
from the very map the run started on. A server with an ``out`` folder leaves the map its
mission made in ``out/known_map`` when it stops (``leave_map``), for the next mission.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from schemas.config_loading import ConfigError, load_config
from server.config import ServerConfig
from server.core import ServerCore
from server.knownmap import ghosts
from server.knownmap.mapdata import KnownMap
from server.runtime import snapshot
from server.runtime.journal import SEGMENT_GLOB, replay
from server.runtime.mapstore import FOLDER, MapError, read_map, write_map

log = logging.getLogger(__name__)


def find_map(path: str | Path, site: str | None = None) -> tuple[KnownMap, str]:
    """The map at ``path`` and where it came from (one line); ``MapError`` when there is
    none. ``site``: the building this run is in (a map of another is refused)."""
    p = Path(path)
    if not p.exists():
        raise MapError(f"{p}: no such folder")
    if not p.is_dir():
        raise MapError(f"{p}: not a folder (a run folder, a state folder or a known_map "
                       "folder is)")
    if any(p.glob(SEGMENT_GLOB)):     # a state folder (its known_map is where it started)
        return map_from_state(p, site), f"the state in {p}, replayed"
    for folder in (p, p / FOLDER, p / "server" / FOLDER):
        if (folder / "map.json").exists():
            return read_map(folder, site), f"the map in {folder}"
    for state in (p / "state", p / "server" / "state"):
        if any(state.glob(SEGMENT_GLOB)):
            return map_from_state(state, site), f"the state in {state}, replayed"
    raise MapError(f"{p}: holds no map (no {FOLDER}/map.json and no state folder with a "
                   "journal)")


def start_map(cfg: ServerConfig, state: Path | None) -> KnownMap | None:
    """The map a run starts on: the state folder's copy when there is one (a resumed run
    keeps the map it started on), none for a resumed run that started without one, else
    ``known_map.path``'s (then copied into the state folder); None without either."""
    if state is not None and (state / FOLDER / "map.json").exists():
        return read_map(state / FOLDER)
    path = cfg.known_map.path
    if state is not None and any(state.glob(SEGMENT_GLOB)):
        if path is not None:
            log.warning("known_map.path %s left aside: the run resumed from %s started "
                        "without a map (an empty state_dir starts a run on it)", path, state)
        return None
    if path is None:
        return None
    known, where = find_map(path, cfg.known_map.site)
    log.warning("known map: %d keyframes made by %d mission(s), from %s; %s mode", len(known),
                known.missions, where, cfg.known_map.mode)
    if state is not None:
        write_map(known, state / FOLDER, cfg.known_map.site, written_by=str(path))
    return known


def mission_map(core: ServerCore) -> KnownMap | None:
    """The map a mission leaves: the known map as the mission kept it (``localize``) or
    extended it (``extend``); on no known map, its largest team's map. None: no keyframes."""
    if core.known is not None:
        return core.known.mission_map()
    team = ghosts.largest_team(core.fleet)
    return None if team is None else ghosts.team_map(core.fleet, team, 1, {})


def leave_map(core: ServerCore, out: Path, cfg: ServerConfig) -> None:
    """Write the mission's map to ``out/known_map`` (for ``--map``), if it has one."""
    known = mission_map(core)
    if known is not None:
        folder = write_map(known, Path(out) / FOLDER, cfg.known_map.site,
                           written_by="mrslam server")
        log.info("the mission's map (%d keyframes) written to %s", len(known), folder)


def map_from_state(state: Path, site: str | None = None) -> KnownMap:
    """The map of a state folder: its server brought back and its map harvested."""
    run_site = _site_of(state)
    if site and run_site and run_site != site:
        raise MapError(f"{state}: a run in {run_site!r}, but this run is in {site!r}")
    cfg = _config_of(state)
    base = read_map(state / FOLDER) if (state / FOLDER / "map.json").exists() else None
    t0 = time.monotonic()
    core, since = None, 0
    if _readable_snapshot(state):
        loaded = snapshot.Snapshots(state).load()
        if loaded is not None:
            core, since = loaded
    if core is None:
        core = ServerCore(cfg, navigate=False, known=base)
    report = replay(core, state, from_sequence=since)
    if report.entries and report.unreadable == report.entries and since == 0:
        raise MapError(f"{state}: none of its journal's {report.entries} records reads in "
                       "this release (written by an incompatible one)")
    known = mission_map(core)
    if known is None:
        raise MapError(f"{state}: its journal holds no keyframes to make a map of")
    log.warning("map of %d keyframes from %s: snapshot %s, %d journal record(s) replayed in "
                "%.1f s", len(known), state, since if since else "none",
                report.entries - report.skipped, time.monotonic() - t0)
    return known


def _readable_snapshot(state: Path) -> bool:
    """Whether a snapshot in ``state`` was written by this very code (else its journal is
    replayed whole): a look at the headers only."""
    n = len(snapshot.MAGIC)
    for path in state.glob("snapshot-*.pkl"):
        try:
            with path.open("rb") as f:
                head = f.read(n + 8 + 64)
        except OSError:
            continue
        if head[:n] == snapshot.MAGIC and len(head) == n + 72:
            version = head[n + 8:].decode(errors="replace").strip()
            if version == snapshot.VERSION:
                return True
    return False


def _config_of(state: Path) -> ServerConfig:
    """The configuration the state was made with (its server's ``server_config.yaml``,
    beside the state folder), without its bus, paths or known map; defaults without one."""
    path = state.parent / "server_config.yaml"
    if not path.exists():
        return ServerConfig()
    try:
        cfg = load_config(ServerConfig, path, environ={})
    except ConfigError as e:
        raise MapError(f"{path}: the configuration of the run does not load in this release "
                       f"({e})") from None
    return cfg.model_copy(update={"out": None, "state_dir": None, "journal": False})


def _site_of(state: Path) -> str | None:
    """The world of the demo run the state belongs to, if it says (its report)."""
    for report in (state.parent / "report.json", state.parent.parent / "report.json"):
        try:
            world = json.loads(report.read_text()).get("world")
        except (OSError, ValueError, AttributeError):
            continue
        if world:
            return Path(str(world)).stem
    return None
