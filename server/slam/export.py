"""Writing maps: nav2 ``map_server`` format (PNG + YAML) and PLY point clouds."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas import nav2map
from server.slam.grid import OccupancyGrid


def nav2_image(grid: OccupancyGrid) -> NDArray[np.uint8]:
    """The trinary image nav2 reads (``schemas.nav2map``), +y up."""
    return nav2map.image(grid.free_mask(), grid.occupied_mask())


def write_nav2(grid: OccupancyGrid, out_dir: Path, name: str = "map") -> Path:
    """Write ``name.png`` and ``name.yaml`` (nav2 map_server, trinary mode); returns the YAML.
    The image is made and compressed a strip of tiles at a time, never whole."""
    def strips() -> Iterator[NDArray[np.uint8]]:
        for _, q in grid.bands(top_first=True):
            yield nav2map.image(grid.free_of(q), grid.occupied_of(q))

    h, w = grid.shape
    return nav2map.write_strips(out_dir, name, w, h, strips, grid.resolution_m,
                                grid.origin_pose[:2])


def write_ply(path: Path, points_xy: NDArray[np.float64] | Sequence[NDArray[np.float64]]
              ) -> None:
    """Binary little-endian PLY of (N, 2) points at z = 0 (float32 x, y, z); the points may
    come in parts (``mapping.point_cloud_parts``), written one after the other."""
    parts = [points_xy] if isinstance(points_xy, np.ndarray) else list(points_xy)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {sum(len(p) for p in parts)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        for part in parts:
            pts = np.zeros((len(part), 3), dtype="<f4")
            pts[:, :2] = part
            pts.tofile(f)


def read_ply_xy(path: Path) -> NDArray[np.float64]:
    """Read back a PLY written by ``write_ply`` (for tests and tools)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n = int(data[:end].decode().split("element vertex ")[1].split()[0])
    pts = np.frombuffer(data[end:end + 12 * n], dtype="<f4").reshape(n, 3)
    return pts[:, :2].astype(np.float64)
