"""nav2 map files (``map_server``'s YAML + image, trinary mode): the project's one writer.

The server's team maps, ``slam-log``'s map and the simulator's true maps are all written here,
so every map we hand to nav2 reads back the same way. In trinary mode map_server turns a pixel
``v`` into ``p = (255 - v) / 255`` (``1 - p`` with ``negate``) and calls the cell occupied when
``p > occupied_thresh``, free when ``p < free_thresh``, unknown otherwise. Our three pixel
values and the two thresholds sit well apart, so a reader that rounds a little (or a threshold
edited to two decimals) still gets back exactly the cells written:

=========  =====  ==========  =========================================
cell       pixel  p           margin to the nearest threshold
=========  =====  ==========  =========================================
free       254    0.0039      0.096 below ``FREE_THRESH`` (0.10)
unknown    205    0.196       0.096 above it, 0.45 below ``OCCUPIED_THRESH``
occupied   0      1.0         0.35 above ``OCCUPIED_THRESH`` (0.65)
=========  =====  ==========  =========================================

Grids here are (H, W) with row 0 at the lowest y (the world's convention); the image's first
row is the largest y, as map_server expects. Files are replaced whole (written beside, flushed,
renamed), so a reader never sees half a map. Needs numpy and yaml only.
"""

from __future__ import annotations

import itertools
import os
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

FREE_PIXEL, UNKNOWN_PIXEL, OCCUPIED_PIXEL = 254, 205, 0
FREE_THRESH, OCCUPIED_THRESH = 0.10, 0.65
IMAGE_FORMATS = ("png", "pgm")


def image(free: NDArray[np.bool_], occupied: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """The trinary image of a grid's masks (occupied wins where both are set), +y up."""
    if free.shape != occupied.shape or free.ndim != 2:
        raise ValueError(f"free {free.shape} and occupied {occupied.shape} masks must be one "
                         "(H, W) shape")
    img = np.full(free.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    img[free] = FREE_PIXEL
    img[occupied] = OCCUPIED_PIXEL
    return np.ascontiguousarray(img[::-1])


def _chunk(tag: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + tag + data
            + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))


def png_stream(width: int, height: int, strips: Iterable[NDArray[np.uint8]]
               ) -> Iterator[bytes]:
    """An 8-bit greyscale PNG, in pieces, of the image made of ``strips`` (rows of ``width``
    pixels each, top first): only one strip is held at a time."""
    yield b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height,
                                                            8, 0, 0, 0, 0))
    z = zlib.compressobj(6)
    rows = 0
    for strip in strips:
        if strip.ndim != 2 or strip.shape[1] != width:
            raise ValueError(f"a strip of shape {strip.shape} in an image {width} wide")
        rows += strip.shape[0]
        raw = np.concatenate([np.zeros((strip.shape[0], 1), dtype=np.uint8),
                              strip.astype(np.uint8, copy=False)], axis=1).tobytes()
        data = z.compress(raw)
        if data:
            yield _chunk(b"IDAT", data)
    if rows != height:
        raise ValueError(f"strips gave {rows} rows for an image {height} high")
    yield _chunk(b"IDAT", z.flush())
    yield _chunk(b"IEND", b"")


def replace_file(path: Path, data: bytes | Iterable[bytes]) -> None:
    """Write ``data`` (bytes, or pieces of it) beside ``path``, flush it to disk, then rename
    it over ``path``."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with tmp.open("wb") as f:
            for piece in [data] if isinstance(data, bytes) else data:
                f.write(piece)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write(out_dir: str | Path, name: str, free: NDArray[np.bool_],
          occupied: NDArray[np.bool_], resolution_m: float,
          origin_xy: Sequence[float], formats: Sequence[str] = ("png",)) -> Path:
    """Write ``name.<format>`` for each format and ``name.yaml`` (naming the first image) into
    ``out_dir``; returns the YAML's path. ``origin_xy``: the world position of the lower-left
    corner of cell (0, 0) [m]."""
    img = image(free, occupied)
    return write_strips(out_dir, name, img.shape[1], img.shape[0], lambda: iter([img]),
                        resolution_m, origin_xy, formats)


def write_strips(out_dir: str | Path, name: str, width: int, height: int,
                 strips: Callable[[], Iterator[NDArray[np.uint8]]], resolution_m: float,
                 origin_xy: Sequence[float], formats: Sequence[str] = ("png",)) -> Path:
    """``write`` for an image too big to hold at once: ``strips()`` gives its trinary pixels a
    strip of rows at a time, top first (called once per format)."""
    if not formats or any(f not in IMAGE_FORMATS for f in formats):
        raise ValueError(f"image formats must be among {IMAGE_FORMATS}, got {list(formats)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for fmt in formats:
        if fmt == "png":
            replace_file(out / f"{name}.png", png_stream(width, height, strips()))
        else:
            head = f"P5\n{width} {height}\n255\n".encode()
            replace_file(out / f"{name}.{fmt}",
                         itertools.chain([head], (s.astype(np.uint8).tobytes()
                                                  for s in strips())))
    meta = {"image": f"{name}.{formats[0]}", "mode": "trinary",
            "resolution": float(resolution_m),
            "origin": [float(origin_xy[0]), float(origin_xy[1]), 0.0], "negate": 0,
            "occupied_thresh": OCCUPIED_THRESH, "free_thresh": FREE_THRESH}
    path = out / f"{name}.yaml"
    replace_file(path, yaml.safe_dump(meta, sort_keys=False).encode())
    return path
