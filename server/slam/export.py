"""Writing maps: nav2 ``map_server`` format (PNG + YAML) and PLY point clouds."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from server.slam.grid import OccupancyGrid

FREE_PIXEL, OCCUPIED_PIXEL, UNKNOWN_PIXEL = 254, 0, 205


def write_png_gray(path: Path, image: NDArray[np.uint8]) -> None:
    """8-bit greyscale PNG, first row at the top (no dependency beyond zlib)."""
    img = np.ascontiguousarray(image, dtype=np.uint8)
    h, w = img.shape
    raw = np.concatenate([np.zeros((h, 1), dtype=np.uint8), img], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    header = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    path.write_bytes(png)


def nav2_image(grid: OccupancyGrid) -> NDArray[np.uint8]:
    """Trinary image: free 254, occupied 0, unknown 205; flipped so that +y is up."""
    img = np.full(grid.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    img[grid.free_mask()] = FREE_PIXEL
    img[grid.occupied_mask()] = OCCUPIED_PIXEL
    return img[::-1]


def write_nav2(grid: OccupancyGrid, out_dir: Path, name: str = "map") -> Path:
    """Write ``name.png`` and ``name.yaml`` (nav2 map_server, trinary mode); returns the YAML."""
    out_dir.mkdir(parents=True, exist_ok=True)
    write_png_gray(out_dir / f"{name}.png", nav2_image(grid))
    meta = {
        "image": f"{name}.png",
        "mode": "trinary",
        "resolution": float(grid.resolution_m),
        "origin": list(grid.origin_pose),
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,  # 205 (unknown) reads as p 0.19608: neither free nor occupied
    }
    path = out_dir / f"{name}.yaml"
    path.write_text(yaml.safe_dump(meta, sort_keys=False))
    return path


def write_ply(path: Path, points_xy: NDArray[np.float64]) -> None:
    """Binary little-endian PLY of (N, 2) points at z = 0 (float32 x, y, z)."""
    pts = np.zeros((len(points_xy), 3), dtype="<f4")
    pts[:, :2] = points_xy
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(pts)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    path.write_bytes(header.encode("ascii") + pts.tobytes())


def read_ply_xy(path: Path) -> NDArray[np.float64]:
    """Read back a PLY written by ``write_ply`` (for tests and tools)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n = int(data[:end].decode().split("element vertex ")[1].split()[0])
    pts = np.frombuffer(data[end:end + 12 * n], dtype="<f4").reshape(n, 3)
    return pts[:, :2].astype(np.float64)
