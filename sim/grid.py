"""Occupancy grids in nav2's convention: rasterise a world, read and write nav2 map files.

A grid is int8 (H, W): -1 unknown, 0..100 occupancy [%]; row index = y, column index = x;
``origin`` is the world (x, y, 0) of the lower-left corner of cell (0, 0). On disk the image is
flipped vertically (first image row = largest y), as nav2's map_server expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import cv2.utils.logging as cv2_logging
import numpy as np

from schemas import nav2map
from schemas.occupancy import FREE, OCCUPIED, UNKNOWN
from schemas.textfile import UnreadableFile, read_yaml
from sim.errors import WorldError
from sim.world import World

_SHIFT = 8  # sub-pixel bits for cv2 drawing
#: a world's obstacles and a map's origin lie within this of zero [m]: beyond, a float's
#: precision no longer tells cells apart (and no building is that large)
MAX_EXTENT_M = 1e6
# the thresholds our maps are written with (schemas.nav2map), also the defaults when reading
OCCUPIED_THRESH, FREE_THRESH = nav2map.OCCUPIED_THRESH, nav2map.FREE_THRESH


@dataclass(frozen=True)
class OccupancyGrid:
    cells: np.ndarray
    resolution_m: float
    origin: tuple[float, float, float]

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.cells.shape
        return h, w

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) world points [m] -> (N, 2) integer (row, col) indices (may be outside)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        col = np.floor((p[:, 0] - self.origin[0]) / self.resolution_m).astype(np.int64)
        row = np.floor((p[:, 1] - self.origin[1]) / self.resolution_m).astype(np.int64)
        return np.column_stack([row, col])

    def area_m2(self, value: int) -> float:
        return float(np.count_nonzero(self.cells == value)) * self.resolution_m ** 2


def rasterise(world: World, resolution_m: float, margin_m: float = 1.0,
              mark_exterior: bool = True) -> OccupancyGrid:
    """Ground-truth grid of ``world``: obstacles 100, free 0.

    A cell is occupied when an obstacle covers its centre or an obstacle's outline passes
    through it, so walls thinner than a cell stay closed. With ``mark_exterior`` the free space
    connected (4-neighbourhood) to the grid's border — the outside of the building — is set to
    unknown (-1), leaving free only the space enclosed by obstacles.
    """
    if not resolution_m > 0:
        raise ValueError(f"resolution must be > 0, got {resolution_m}")
    bounds = world.bounds()
    if not all(math.isfinite(v) and abs(v) <= MAX_EXTENT_M for v in bounds):
        raise WorldError(f"{world.source}: obstacles reach beyond {MAX_EXTENT_M:g} m of the "
                         f"origin (bounds {bounds})")
    xmin, ymin, xmax, ymax = bounds
    ox, oy = xmin - margin_m, ymin - margin_m
    w = math.ceil((xmax + margin_m - ox) / resolution_m)
    h = math.ceil((ymax + margin_m - oy) / resolution_m)
    if w * h > 20000 * 20000:
        raise WorldError(f"{world.source}: a {w}x{h} grid at {resolution_m:g} m per cell is "
                         "too large; use a coarser resolution")
    occ = np.zeros((h, w), np.uint8)
    scale = (1 << _SHIFT) / resolution_m

    def to_px(p: np.ndarray) -> np.ndarray:
        # pixel centres sit at integer coordinates: cell j spans [j - 0.5, j + 0.5)
        q = (np.asarray(p, np.float64) - (ox, oy)) * scale - 0.5 * (1 << _SHIFT)
        return np.rint(q).astype(np.int32)

    polys = [to_px(p) for p in world.polygons]
    if polys:
        cv2.fillPoly(occ, polys, 1, lineType=cv2.LINE_8, shift=_SHIFT)
        cv2.polylines(occ, polys, True, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    for x, y, r in world.circles:
        c = to_px(np.array([x, y]))
        cv2.circle(occ, (int(c[0]), int(c[1])), round(r * scale), 1, -1,
                   cv2.LINE_8, _SHIFT)
    if len(world.segments) and not polys:  # a world given only as outlines (map images)
        seg = world.segments
        lines = [to_px(np.array([[s[0], s[1]], [s[2], s[3]]])) for s in seg]
        cv2.polylines(occ, lines, False, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    cells = np.where(occ > 0, OCCUPIED, FREE).astype(np.int8)
    if mark_exterior:
        cells[exterior_mask(occ == 0)] = UNKNOWN
    return OccupancyGrid(cells, float(resolution_m), (ox, oy, 0.0))


def exterior_mask(free: np.ndarray) -> np.ndarray:
    """Free cells 4-connected to the grid's border."""
    _, labels = cv2.connectedComponents(free.astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    border = border[border > 0]
    return np.isin(labels, border) & free


def free_regions(grid: OccupancyGrid) -> list[float]:
    """Areas [m²] of the 4-connected free regions, largest first."""
    n, labels = cv2.connectedComponents((grid.cells == FREE).astype(np.uint8), connectivity=4)
    counts = np.bincount(labels.ravel(), minlength=n)[1:]
    return sorted((float(c) * grid.resolution_m ** 2 for c in counts), reverse=True)


def wall_face_area_m2(grid: OccupancyGrid) -> float:
    """Area [m²] of the occupied cells that touch (8-neighbourhood) a free cell: the walls as a
    LIDAR sees them from the free space. A map being explored marks these cells too, and
    exploration coverage counts them (explored = free or occupied)."""
    free = (grid.cells == FREE).astype(np.uint8)
    near_free = cv2.dilate(free, np.ones((3, 3), np.uint8)).astype(bool)
    return float(np.count_nonzero(near_free & (grid.cells == OCCUPIED))) * grid.resolution_m ** 2


# -- nav2 map files ----------------------------------------------------------------------------
def write_nav2(grid: OccupancyGrid, out_dir: str | Path, name: str = "map") -> Path:
    """Write ``name.pgm``, ``name.png`` and ``name.yaml`` (trinary, ``schemas.nav2map``)."""
    p = grid.cells.astype(np.float64) / OCCUPIED
    free = (grid.cells != UNKNOWN) & (p < FREE_THRESH)
    occupied = p > OCCUPIED_THRESH
    return nav2map.write(out_dir, name, free, occupied, grid.resolution_m, grid.origin[:2],
                         formats=("pgm", "png"))


def read_nav2(yaml_path: str | Path) -> OccupancyGrid:
    """Read a nav2 map (YAML + PGM/PNG image) as a grid; errors name the file and field."""
    path = Path(yaml_path)
    try:
        meta = read_yaml(path, "a nav2 map's .yaml is YAML text")
    except UnreadableFile as e:
        raise WorldError(str(e)) from None
    if not isinstance(meta, dict):
        raise WorldError(f"{path}: {'is empty; ' if meta is None else ''}expected a mapping "
                         "with image, resolution and origin")
    for key in ("image", "resolution", "origin"):
        if key not in meta:
            raise WorldError(f"{path}: missing '{key}'")
    if not isinstance(meta["image"], str) or not meta["image"].strip():
        raise WorldError(f"{path}: image must name the map's image file")
    try:
        res = float(meta["resolution"])
        origin = [float(v) for v in meta["origin"]]
        occ_t = float(meta.get("occupied_thresh", OCCUPIED_THRESH))
        free_t = float(meta.get("free_thresh", FREE_THRESH))
        negate = int(meta.get("negate", 0))
    except (TypeError, ValueError, OverflowError) as e:
        raise WorldError(f"{path}: bad number in resolution/origin/thresholds ({e})") from None
    mode = meta.get("mode", "trinary")
    if not (res > 0 and math.isfinite(res)) or len(origin) != 3:
        raise WorldError(f"{path}: resolution must be > 0 and origin [x, y, yaw]")
    if not all(math.isfinite(v) and abs(v) <= MAX_EXTENT_M for v in origin):
        raise WorldError(f"{path}: origin {origin} must be finite and within "
                         f"{MAX_EXTENT_M:g} m of zero")
    if origin[2] != 0.0:
        raise WorldError(f"{path}: origin yaw {origin[2]} is not supported (must be 0)")
    if not 0.0 <= free_t < occ_t <= 1.0:
        raise WorldError(f"{path}: thresholds must satisfy 0 <= free_thresh < "
                         f"occupied_thresh <= 1 (got {free_t} and {occ_t})")
    if mode not in ("trinary", "scale", "raw"):
        raise WorldError(f"{path}: unknown mode '{str(mode)[:40]}' (trinary, scale or raw)")
    raw = _read_image(path, meta["image"])
    if raw.ndim == 3:
        raw = raw[:, :, :3].mean(axis=2)
    v = np.flipud(raw.astype(np.float64))
    if mode == "raw":
        cells = np.where((v >= FREE) & (v <= OCCUPIED), v, UNKNOWN).astype(np.int8)
        return OccupancyGrid(cells, res, (origin[0], origin[1], 0.0))
    p = v / 255.0 if negate else (255.0 - v) / 255.0
    cells = np.full(v.shape, UNKNOWN, np.int8)
    cells[p < free_t] = FREE
    if mode == "trinary":
        cells[p > occ_t] = OCCUPIED
    else:
        mid = (p >= free_t) & (p <= occ_t)
        cells[mid] = np.rint(99 * (p[mid] - free_t) / (occ_t - free_t)).astype(np.int8)
        cells[p > occ_t] = OCCUPIED
    return OccupancyGrid(cells, res, (origin[0], origin[1], 0.0))


def _read_image(yaml_path: Path, name: str) -> np.ndarray:
    """The map's image (``name`` relative to the YAML's folder), decoded here rather than by
    ``cv2.imread``, which says nothing of why a file failed and warns on stderr."""
    image = yaml_path.parent / name
    try:
        data = image.read_bytes()
    except FileNotFoundError:
        raise WorldError(f"{yaml_path}: image '{name}' not found ({image})") from None
    except OSError as e:
        raise WorldError(f"{yaml_path}: image '{name}': cannot read ({e.strerror})") from None
    if not data:
        raise WorldError(f"{yaml_path}: image '{name}' is empty")
    level = cv2_logging.getLogLevel()
    cv2_logging.setLogLevel(cv2_logging.LOG_LEVEL_ERROR)  # a damaged file: no warning lines
    try:
        raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:           # e.g. more pixels than OpenCV reads
        raise WorldError(f"{yaml_path}: image '{name}' cannot be decoded "
                         f"({' '.join(str(getattr(e, 'err', e)).split())})") from None
    finally:
        cv2_logging.setLogLevel(level)
    if raw is None or raw.size == 0:
        raise WorldError(f"{yaml_path}: image '{name}' is not an image (PGM, PNG, ...) or is "
                         "damaged")
    return np.asarray(raw)
