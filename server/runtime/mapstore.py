"""Known maps on disk: the folder a mission leaves (``known_map/``), and finding a map in what
a previous mission left.

A ``known_map`` folder holds ``map.json`` (the format and its version, the site, how many
keyframes, the frame's anchor, how many missions made it) and ``keyframes.npz`` (every
keyframe's pose, stamp, odometry, matching points with normals and ranges, and the points its
map is drawn from). It does not depend on the code that wrote it, unlike a snapshot: a later
release reads it as long as the format's version is one it knows.

``find_map`` takes what a user names — a run folder, a server's folder, a state folder or a
``known_map`` folder — and returns the map in it:

1. a ``known_map`` folder (the map a server writes when it stops) is read as it is;
2. else a state folder is brought back as a resumed server would (its newest snapshot that this
   code can read, then its journal replayed; a map written by an older release has no
   ``known_map`` folder and no snapshot this code reads, so its journal is replayed whole) and
   its largest team's keyframes make the map;
3. else, or when neither reads, ``MapError`` says in one line what is wrong.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from server.knownmap.mapdata import KnownMap
from server.slam.keyframes import Keyframe
from server.slam.render_store import RenderScan
from server.slam.scan import ScanPoints

log = logging.getLogger(__name__)

FORMAT = "mrslam-known-map"
FORMAT_VERSION = 1
FOLDER = "known_map"
_ARRAYS = ("poses", "stamps", "odom", "fov", "heading", "n_match", "points", "normals",
           "ranges", "n_hits", "n_misses", "render", "sources")


class MapError(ValueError):
    """A map that cannot be used: missing, damaged, of an unknown format, or of another
    site. The CLI says it in one line (exit code 2)."""

    user_error = True


# -- writing -----------------------------------------------------------------------------------
def write_map(known: KnownMap, folder: Path, site: str | None = None,
              written_by: str = "") -> Path:
    """Write ``known`` as a ``known_map`` folder at ``folder`` (replaced whole: written
    beside, then renamed over the old one). Returns the folder."""
    kfs = known.keyframes
    match = [kf.matchable for kf in kfs]
    renders = [kf.render.points() for kf in kfs]
    arrays: dict[str, Any] = {
        "poses": known.poses, "stamps": known.stamps_ns,
        "odom": np.array([kf.T_odom_robot for kf in kfs]).reshape(-1, 3),
        "fov": np.array([m.fov_rad for m in match], dtype=np.float64),
        "heading": np.array([m.heading_rad for m in match], dtype=np.float64),
        "n_match": np.array([len(m.points) for m in match], dtype=np.int64),
        "points": _stack([m.points for m in match], np.float64),
        "normals": _stack([m.normals for m in match], np.float64),
        "ranges": np.concatenate([m.ranges_m for m in match]) if kfs else np.zeros(0),
        "n_hits": np.array([len(h) for h, _ in renders], dtype=np.int64),
        "n_misses": np.array([len(m) for _, m in renders], dtype=np.int64),
        "render": _stack([np.concatenate([h, m]) for h, m in renders], np.float32),
        "sources": np.array(known.sources, dtype=str),
    }
    head = {"format": FORMAT, "version": FORMAT_VERSION, "site": site,
            "keyframes": len(known), "anchor": known.anchor, "missions": known.missions,
            "resolution_m": known.resolution_m, "written_by": written_by,
            "written_at": time.strftime("%Y-%m-%dT%H:%M:%S"), "notes": known.notes}
    folder = Path(folder)
    tmp = folder.with_name(f".{folder.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    with (tmp / "keyframes.npz").open("wb") as f:
        np.savez_compressed(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    (tmp / "map.json").write_text(json.dumps(head, indent=2))
    old = folder.with_name(f".{folder.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if folder.exists():
        folder.rename(old)
    tmp.rename(folder)
    shutil.rmtree(old, ignore_errors=True)
    return folder


def _stack(parts: list[Any], dtype: type) -> np.ndarray:
    return (np.concatenate(parts).astype(dtype) if parts else np.zeros((0, 2), dtype))


# -- reading -----------------------------------------------------------------------------------
def read_map(folder: Path, site: str | None = None, spill: bool = True) -> KnownMap:
    """The map of a ``known_map`` folder; ``MapError`` naming what is wrong. ``site``: the
    building this run is in (a map written for another is refused)."""
    folder = Path(folder)
    head = _head(folder)
    if site and head.get("site") and head["site"] != site:
        raise MapError(f"{folder}: a map of {head['site']!r}, but this run is in {site!r}")
    try:
        with np.load(folder / "keyframes.npz", allow_pickle=False) as z:
            a = {k: z[k] for k in _ARRAYS}
    except FileNotFoundError:
        raise MapError(f"{folder}: keyframes.npz is missing") from None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as e:
        raise MapError(f"{folder}: keyframes.npz is damaged ({e})") from None
    try:
        keyframes = _keyframes(a, spill)
    except (ValueError, IndexError) as e:
        raise MapError(f"{folder}: keyframes.npz does not hold a map ({e})") from None
    if len(keyframes) != head.get("keyframes", len(keyframes)):
        raise MapError(f"{folder}: map.json says {head['keyframes']} keyframes, "
                       f"keyframes.npz holds {len(keyframes)}")
    return KnownMap(keyframes, a["poses"], [str(s) for s in a["sources"]],
                    float(head.get("resolution_m", 0.05)), str(head.get("anchor", "")),
                    int(head.get("missions", 1)), dict(head.get("notes") or {}))


def _head(folder: Path) -> dict[str, Any]:
    try:
        head = json.loads((folder / "map.json").read_text())
    except FileNotFoundError:
        raise MapError(f"{folder}: no map.json (not a known_map folder)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise MapError(f"{folder}: map.json does not read ({e})") from None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise MapError(f"{folder}: map.json is not an mrslam map")
    if head.get("version") != FORMAT_VERSION:
        raise MapError(f"{folder}: a map of format version {head.get('version')}; this "
                       f"release reads version {FORMAT_VERSION}")
    return head


def _keyframes(a: dict[str, np.ndarray], spill: bool) -> list[Keyframe]:
    n = len(a["poses"])
    if a["poses"].shape != (n, 3) or not np.isfinite(a["poses"]).all() or n == 0:
        raise ValueError("no keyframes, or poses that are not finite (K, 3)")
    for name in ("stamps", "odom", "fov", "heading", "n_match", "n_hits", "n_misses",
                 "sources"):
        if len(a[name]) != n:
            raise ValueError(f"{name} has {len(a[name])} rows for {n} keyframes")
    m_at = np.concatenate([[0], np.cumsum(a["n_match"])])
    r_at = np.concatenate([[0], np.cumsum(a["n_hits"] + a["n_misses"])])
    if m_at[-1] != len(a["points"]) or r_at[-1] != len(a["render"]) or \
            len(a["normals"]) != len(a["points"]) or len(a["ranges"]) != len(a["points"]):
        raise ValueError("point counts do not add up")
    out = []
    for k in range(n):
        s, e = m_at[k], m_at[k + 1]
        match = ScanPoints(_ro(a["points"][s:e]), _ro(a["normals"][s:e]), _ro(a["ranges"][s:e]),
                           _ro(np.zeros((0, 2))), _ro(np.zeros((0, 2))), float(a["fov"][k]),
                           float(a["heading"][k]))
        q = np.ascontiguousarray(a["render"][r_at[k]:r_at[k + 1]], dtype=np.float32)
        out.append(Keyframe(k, int(a["stamps"][k]), _ro(a["odom"][k]), match,
                            RenderScan(q, int(a["n_hits"][k]), spill)))
    return out


def _ro(x: np.ndarray) -> np.ndarray:
    y = np.array(x, dtype=np.float64)
    y.flags.writeable = False
    return y
