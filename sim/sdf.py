"""Load a Gazebo SDF world (or a single model file) as a 2D world in the LIDAR plane.

``<include>`` of ``model://NAME`` is resolved against a model path (``models/`` beside the world,
the world's folder, then ``GAZEBO_MODEL_PATH``, then any explicit paths), reading the model's
``model.config`` for its SDF file. Poses are composed parent → model → link → collision. As in
sdformat, an ``<include>``'s ``<pose>`` replaces the included model's own top-level ``<pose>``
(the model file's pose only applies when the include gives none).

Collision geometry is cut by the horizontal plane ``z = lidar_height_m``: ``box`` (any
orientation) gives a convex polygon, upright ``cylinder`` and ``sphere`` give circles, and
geometry the plane misses is skipped. ``plane`` geometry is accepted when horizontal (floors).
Anything else (mesh, heightmap, polyline, tilted cylinder...), an unknown model, or a model
without any collision element raises WorldError naming the file and element. Every model is a
static obstacle (Gazebo's dynamics, e.g. of a non-static door, are not simulated).
Gazebo's stock ``sun`` and ``ground_plane`` models need no files: they have nothing in the plane.
"""

from __future__ import annotations

import logging
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import WorldError
from sim.geometry import quat_matrix, rpy_matrix, transform
from sim.world import World, convex_hull

log = logging.getLogger(__name__)

#: Stock Gazebo models with nothing in a LIDAR plane above the floor.
BUILTIN_EMPTY_MODELS = frozenset({"sun", "ground_plane"})
_UNSUPPORTED = ("mesh", "heightmap", "polyline", "capsule", "ellipsoid", "image")
_BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7),
              (0, 4), (1, 5), (2, 6), (3, 7)]


@dataclass
class _Shapes:
    polygons: list[np.ndarray] = field(default_factory=list)
    circles: list[tuple[float, float, float]] = field(default_factory=list)


def load_sdf(path: str | Path, model_path: list[str | Path] | None = None,
             lidar_height_m: float = 0.2) -> World:
    """Load ``path`` (a ``.world``/``.sdf`` file holding a ``<world>`` or a ``<model>``)."""
    path = Path(path)
    search = default_model_path(path, model_path)
    root = _parse(path)
    shapes = _Shapes()
    loader = _Loader(search, lidar_height_m, shapes)
    world_el = root.find("world")
    if world_el is not None:
        loader.container(world_el, np.eye(4), path, "world")
    else:
        models = root.findall("model")
        if not models:
            raise WorldError(f"{path}: no <world> or <model> element under <{root.tag}>")
        for m in models:
            loader.model(m, np.eye(4), path, None)
    if not shapes.polygons and not shapes.circles:
        raise WorldError(f"{path}: no collision geometry crosses the LIDAR plane "
                         f"z = {lidar_height_m} m")
    return World.from_shapes(path.stem, str(path), shapes.polygons, shapes.circles, lidar_height_m)


def default_model_path(world_path: Path, extra: list[str | Path] | None = None) -> list[Path]:
    paths = [world_path.parent / "models", world_path.parent]
    paths += [Path(p) for p in os.environ.get("GAZEBO_MODEL_PATH", "").split(os.pathsep) if p]
    paths += [Path(p) for p in extra or []]
    return paths


def _parse(path: Path) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except FileNotFoundError:
        raise WorldError(f"{path}: no such world file") from None
    except OSError as e:
        raise WorldError(f"{path}: cannot read ({e.strerror})") from None
    except ET.ParseError as e:
        raise WorldError(f"{path}: not valid XML ({e})") from None


def _where(el: ET.Element, name: str | None = None) -> str:
    n = name if name is not None else el.get("name")
    return f"<{el.tag} name='{n}'>" if n else f"<{el.tag}>"


def parse_pose(el: ET.Element | None, file: Path) -> np.ndarray:
    """4x4 transform of a ``<pose>`` (``x y z roll pitch yaw``, or ``x y z qx qy qz qw``)."""
    if el is None:
        return np.eye(4)
    rel = el.get("relative_to") or el.get("frame")
    if rel:
        raise WorldError(f"{file}: <pose relative_to='{rel}'>: poses relative to named frames "
                         "are not supported")
    try:
        v = [float(t) for t in (el.text or "").split()]
    except ValueError:
        raise WorldError(f"{file}: <pose>{el.text}</pose>: not numbers") from None
    if not all(math.isfinite(x) for x in v):
        raise WorldError(f"{file}: <pose>{el.text}</pose>: not finite")
    quat = el.get("rotation_format", "euler_rpy") == "quat_xyzw"
    if len(v) != (7 if quat else 6):
        raise WorldError(f"{file}: <pose>{el.text}</pose>: expected {7 if quat else 6} numbers")
    if quat:
        try:
            R = quat_matrix(*v[3:])
        except ValueError as e:
            raise WorldError(f"{file}: <pose>{el.text}</pose>: {e}") from None
    else:
        rpy = v[3:]
        if el.get("degrees", "false").strip().lower() in ("true", "1"):
            rpy = [math.radians(a) for a in rpy]
        R = rpy_matrix(*rpy)
    return transform(R, (v[0], v[1], v[2]))


def _floats(el: ET.Element, tag: str, n: int, file: Path, where: str) -> list[float]:
    sub = el.find(tag)
    if sub is None:
        raise WorldError(f"{file}: {where}: missing <{tag}>")
    try:
        v = [float(t) for t in (sub.text or "").split()]
    except ValueError:
        v = []
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise WorldError(f"{file}: {where}: <{tag}>{sub.text}</{tag}> is not {n} numbers")
    return v


class _Loader:
    def __init__(self, search: list[Path], z: float, out: _Shapes) -> None:
        self.search = search
        self.z = z
        self.out = out
        self._depth = 0

    # -- containers -------------------------------------------------------------------------
    def container(self, el: ET.Element, T_parent: np.ndarray, file: Path, what: str) -> int:
        """Models and includes inside a world or model; returns the number of collisions."""
        n = 0
        for child in el:
            if child.tag == "model":
                n += self.model(child, T_parent, file, None)
            elif child.tag == "include":
                n += self.include(child, T_parent, file)
        return n

    def include(self, el: ET.Element, T_parent: np.ndarray, file: Path) -> int:
        uri_el = el.find("uri")
        uri = (uri_el.text or "").strip() if uri_el is not None else ""
        if not uri:
            raise WorldError(f"{file}: <include> without <uri>")
        name = uri[len("model://"):] if uri.startswith("model://") else uri
        if name.rstrip("/") in BUILTIN_EMPTY_MODELS and self._find(name) is None:
            log.debug("%s: stock model %s has nothing in the LIDAR plane", file, uri)
            return 0
        model_file = self._find(name)
        if model_file is None:
            raise WorldError(f"{file}: <include><uri>{uri}</uri>: unknown model (searched "
                             f"{', '.join(str(p) for p in self.search)})")
        root = _parse(model_file)
        models = root.findall("model")
        if len(models) != 1:
            raise WorldError(f"{model_file}: expected one <model>, found {len(models)}")
        pose_el = el.find("pose")
        override = parse_pose(pose_el, file) if pose_el is not None else None
        if self._depth > 16:
            raise WorldError(f"{file}: <include><uri>{uri}</uri>: includes nested too deeply")
        self._depth += 1
        try:
            n = self.model(models[0], T_parent, model_file, override)
        finally:
            self._depth -= 1
        if n == 0:
            raise WorldError(f"{model_file}: {_where(models[0])} (included as {uri}) has no "
                             "links with <collision> geometry")
        return n

    def _find(self, name: str) -> Path | None:
        for base in self.search:
            d = base / name
            if not d.is_dir():
                continue
            cfg = d / "model.config"
            if cfg.is_file():
                sdf = _parse(cfg).find("sdf")
                if sdf is not None and (sdf.text or "").strip():
                    return d / (sdf.text or "").strip()
            if (d / "model.sdf").is_file():
                return d / "model.sdf"
        return None

    def model(self, el: ET.Element, T_parent: np.ndarray, file: Path,
              pose_override: np.ndarray | None) -> int:
        T_model = T_parent @ (pose_override if pose_override is not None
                              else parse_pose(el.find("pose"), file))
        n = self.container(el, T_model, file, "model")
        for link in el.findall("link"):
            T_link = T_model @ parse_pose(link.find("pose"), file)
            for col in link.findall("collision"):
                T_col = T_link @ parse_pose(col.find("pose"), file)
                where = f"{_where(el)} {_where(link)} {_where(col)}"
                self.geometry(col.find("geometry"), T_col, file, where)
                n += 1
        if n == 0 and el.findall("link"):
            raise WorldError(f"{file}: {_where(el)} has links but no <collision> geometry")
        return n

    # -- geometry ---------------------------------------------------------------------------
    def geometry(self, geom: ET.Element | None, T: np.ndarray, file: Path, where: str) -> None:
        if geom is None or len(geom) == 0:
            raise WorldError(f"{file}: {where}: <collision> without <geometry>")
        shape = geom[0]
        kind = shape.tag
        if kind == "box":
            self.box(_floats(shape, "size", 3, file, f"{where} <box>"), T, file, where)
        elif kind == "cylinder":
            r = _floats(shape, "radius", 1, file, f"{where} <cylinder>")[0]
            length = _floats(shape, "length", 1, file, f"{where} <cylinder>")[0]
            self.cylinder(r, length, T, file, where)
        elif kind == "sphere":
            r = _floats(shape, "radius", 1, file, f"{where} <sphere>")[0]
            dz = self.z - T[2, 3]
            if abs(dz) < r:
                self.out.circles.append((T[0, 3], T[1, 3], math.sqrt(r * r - dz * dz)))
        elif kind == "plane":
            normal = T[:3, :3] @ np.array(
                _floats(shape, "normal", 3, file, f"{where} <plane>") if shape.find("normal")
                is not None else [0.0, 0.0, 1.0])
            if abs(normal[2]) < (1 - 1e-6) * np.linalg.norm(normal):
                raise WorldError(f"{file}: {where}: <plane> that is not horizontal is not "
                                 "supported")
        elif kind in _UNSUPPORTED:
            raise WorldError(f"{file}: {where}: <{kind}> geometry is not supported (use box, "
                             "cylinder or sphere collisions)")
        else:
            raise WorldError(f"{file}: {where}: unknown geometry <{kind}>")

    def box(self, size: list[float], T: np.ndarray, file: Path, where: str) -> None:
        if min(size) <= 0:
            raise WorldError(f"{file}: {where}: <box> size {size} must be positive")
        half = np.array(size) / 2.0
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        corners = (T[:3, :3] @ (signs * half).T).T + T[:3, 3]
        z = corners[:, 2]
        if not z.min() < self.z < z.max():
            return
        pts = []
        for i, j in _BOX_EDGES:
            zi, zj = z[i], z[j]
            if (zi - self.z) * (zj - self.z) <= 0 and zi != zj:
                t = (self.z - zi) / (zj - zi)
                pts.append(corners[i, :2] + t * (corners[j, :2] - corners[i, :2]))
        hull = convex_hull(np.array(pts))
        if len(hull) >= 3:
            self.out.polygons.append(hull)

    def cylinder(self, r: float, length: float, T: np.ndarray, file: Path, where: str) -> None:
        axis = T[:3, 2]
        if abs(axis[2]) < 1 - 1e-6:
            raise WorldError(f"{file}: {where}: a tilted <cylinder> is not supported")
        if abs(self.z - T[2, 3]) < length / 2:
            self.out.circles.append((T[0, 3], T[1, 3], r))
