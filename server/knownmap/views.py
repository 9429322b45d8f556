"""What one keyframe sees of another's: its beams by bearing, and how far they reach toward
points; the map a mission leaves with the keyframes newer ones see again dropped. No I/O."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import inverse, transform_points
from server.knownmap.mapdata import KnownMap, harvest
from server.slam.keyframes import Keyframe

F64 = NDArray[np.float64]

#: share of an older keyframe's returns a newer one's beams must reach to supersede it
COVER = 0.8
#: how far short of a return a beam may end and still reach it [m]
REACH_TOL_M = 0.15
#: bearing bins of a keyframe's beams (half a degree)
BINS = 720
#: keyframes of one mission this near each other are of one place (``slam.keyframes``' spacing)
SAME_MISSION_M = 0.5


def beams(kf: Keyframe) -> F64:
    """A keyframe's beams by bearing (``BINS``): how far each reached (a return or the end of
    an empty beam), NaN where it had none; each bin the farthest of it and its neighbours."""
    pts = np.asarray(kf.render.stored(), dtype=np.float64)
    out = np.full(BINS, np.nan)
    if not len(pts):
        return out
    b = _bins(np.arctan2(pts[:, 1], pts[:, 0]))
    np.fmax.at(out, b, np.hypot(pts[:, 0], pts[:, 1]))
    return out


def _bins(bearing: F64) -> NDArray[np.int64]:
    return (np.floor((bearing + math.pi) / (2 * math.pi) * BINS).astype(np.int64)) % BINS


def reach(prof: F64, T_kf: F64, xy: F64) -> tuple[F64, F64]:
    """For points in the map frame: their distance from the keyframe at ``T_kf``, and how far
    its beams toward them reached (the farthest of the nearest three bins; NaN: no beam)."""
    q = transform_points(inverse(T_kf), xy)
    b = _bins(np.arctan2(q[:, 1], q[:, 0]))
    near = np.stack([prof[(b + s) % BINS] for s in (-1, 0, 1)])
    ok = np.isfinite(near).any(axis=0)
    r = np.full(len(b), np.nan)
    r[ok] = np.nanmax(near[:, ok], axis=0)
    return np.hypot(q[:, 0], q[:, 1]), r


def consolidated(known: KnownMap, supersede_m: float) -> tuple[KnownMap, int]:
    """The map a mission leaves, its keyframes that newer ones see again dropped: the rule
    of superseding (``COVER``, within ``supersede_m``), the newest first (by mission, then
    stamp), among this mission's keyframes within ``SAME_MISSION_M`` (its robots passing the
    same place again leave one) and between missions (an earlier one's for a later one's).
    Returns the map and how many were dropped."""
    if supersede_m <= 0 or len(known) < 2:
        return known, 0

    def mission_of(source: str) -> int:
        head = source.split(":", 1)[0]
        return int(head) if head.isdigit() else 0

    missions = [mission_of(s) for s in known.sources]
    last = max(missions)
    order = sorted(range(len(known)), key=lambda k: (missions[k], known.keyframes[k].stamp_ns),
                   reverse=True)
    kept: list[int] = []
    profs: dict[int, F64] = {}
    for k in order:
        kf, T = known.keyframes[k], known.poses[k]
        # a keyframe of an earlier mission goes for a later one's; this mission's keep one
        # per place as one robot's keyframes do (their spacing); earlier missions' own are
        # left as those missions left them
        near = [q for q in kept if math.hypot(*(known.poses[q, :2] - T[:2])) <= (
            supersede_m if missions[q] > missions[k] else
            min(supersede_m, SAME_MISSION_M) if missions[k] == last else -1.0)]
        xy = transform_points(T, np.asarray(kf.hits, np.float64)) if near else np.zeros((0, 2))
        covered = False
        for q in near:
            if q not in profs:
                profs[q] = beams(known.keyframes[q])
            dist, got = reach(profs[q], known.poses[q], xy)
            if len(xy) and np.mean(np.isfinite(got) & (got >= dist - REACH_TOL_M)) >= COVER:
                covered = True
                break
        if not covered:
            kept.append(k)
    keep = sorted(kept)
    if len(keep) == len(known):
        return known, 0
    out = harvest([([known.sources[k] for k in keep], [known.keyframes[k] for k in keep],
                    known.poses[keep])], known.resolution_m, known.anchor, known.missions,
                  known.notes)
    return out, len(known) - len(keep)
