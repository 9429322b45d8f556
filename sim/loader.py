"""Load any supported world file: Gazebo SDF (``.world``/``.sdf``) or a nav2 map (``.yaml``)."""

from __future__ import annotations

from pathlib import Path

from sim.errors import WorldError
from sim.mapworld import load_map_world
from sim.sdf import load_sdf
from sim.world import World


def site_of(path: str | Path) -> str:
    """The building a world file shows: its name up to the first dot. A variant of a site
    (the same building changed: doors closed, boxes moved) is ``<site>.<variant>.world``,
    so a map made in the site is accepted in its variants. Raises WorldError for a name
    without a site (``.changed.world``)."""
    p = Path(path)
    site = p.name.split(".")[0]
    if not site:
        raise WorldError(f"{p}: a world file's name must start with its site "
                         "(<site>.world or <site>.<variant>.world)")
    return site


def load_world(path: str | Path, model_path: list[str | Path] | None = None,
               lidar_height_m: float = 0.2) -> World:
    """The world in ``path``, cut by the plane ``z = lidar_height_m``; raises WorldError."""
    p = Path(path)
    if not p.exists():
        raise WorldError(f"{p}: no such world file")
    suffix = p.suffix.lower()
    if suffix in (".world", ".sdf"):
        return load_sdf(p, model_path, lidar_height_m)
    if suffix in (".yaml", ".yml"):
        return load_map_world(p, lidar_height_m)
    raise WorldError(f"{p}: unknown world format '{suffix}' (expected .world, .sdf or a nav2 "
                     ".yaml)")
