"""How well two maps fit under a proposed transform: cell agreement and scan-to-map matches.

``map_agreement`` counts walls of one grid that fall into the other's open space;
``cross_matches`` matches one robot's keyframes against another's local map and says how far
the overlap turns and shifts them. Both judge a merge (``server.rendezvous.merger``); the
matches also become factors of a team's graph (``server.rendezvous.surgery``). No I/O here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import between, compose, transform_points, wrap_angle
from server.slam import RobotSlam
from server.slam.grid import OccupancyGrid

if TYPE_CHECKING:
    from server.planning.grid import OccupancyGrid as PlanningMap
    from server.slam.icp import PointMap

F64 = NDArray[np.float64]

#: a degenerate match matched again (``cross_matches(hold_weak=True)``) is held this close
#: [m] to the keyframe's placement along its weak direction
HELD_ALONG_SIGMA_M = 0.01
#: ... and its factor knows the position along that direction to this σ [m]: nothing
UNKNOWN_ALONG_SIGMA_M = 10.0


@dataclass(frozen=True)
class MapAgreement:
    overlap_cells: int        # cells known in both grids
    occupied_checked: int     # occupied cells (either grid) inside the overlap
    conflicts: int            # occupied in one where the other is clearly free

    @property
    def conflict_ratio(self) -> float:
        return self.conflicts / self.occupied_checked if self.occupied_checked else 0.0


def map_agreement(grid_a: OccupancyGrid, grid_b: OccupancyGrid, T_ab: F64,
                  tolerance_cells: int = 2) -> MapAgreement:
    """How grid b, moved into a's frame by ``T_ab``, agrees with grid a: an occupied cell of
    either conflicts when the other grid says free there, with no occupied cell within
    ``tolerance_cells`` (walls are a cell or two thick and alignments are not perfect) and
    only free cells one more cell around. A wall that beams grazed is partly erased in a map
    (they cross its cells on their way to hits farther along it), but such free cells still
    border the unknown behind the wall; a wall put into the middle of a room by a wrong
    transform has free space all around."""
    from scipy.ndimage import maximum_filter, minimum_filter

    occ_a, free_a = grid_a.occupied_mask(), grid_a.free_mask()
    occ_b, free_b = grid_b.occupied_mask(), grid_b.free_mask()
    if not occ_a.size or not occ_b.size:
        return MapAgreement(0, 0, 0)
    size = 2 * tolerance_cells + 1
    near_a = maximum_filter(occ_a, size=size)
    near_b = maximum_filter(occ_b, size=size)
    open_a = minimum_filter(free_a, size=size + 2)
    open_b = minimum_filter(free_b, size=size + 2)
    rb, cb = np.nonzero(occ_b | free_b)
    res_b = grid_b.resolution_m
    pts_b = np.stack([grid_b.origin[0] + (cb + 0.5) * res_b,
                      grid_b.origin[1] + (rb + 0.5) * res_b], axis=1)
    c, s = math.cos(T_ab[2]), math.sin(T_ab[2])
    pa = pts_b @ np.array([[c, s], [-s, c]]) + T_ab[:2]
    ij = grid_a.cell_of(pa)
    h, w = occ_a.shape
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    ia, ja = ij[inside, 1], ij[inside, 0]
    rb, cb = rb[inside], cb[inside]
    known_a = occ_a[ia, ja] | free_a[ia, ja]
    ia, ja, rb, cb = ia[known_a], ja[known_a], rb[known_a], cb[known_a]
    b_occ, b_free = occ_b[rb, cb], free_b[rb, cb]
    a_occ, a_free = occ_a[ia, ja], free_a[ia, ja]
    conflicts = int((b_occ & a_free & ~near_a[ia, ja] & open_a[ia, ja]).sum()
                    + (a_occ & b_free & ~near_b[rb, cb] & open_b[rb, cb]).sum())
    checked = int((b_occ | a_occ).sum())
    return MapAgreement(len(ia), checked, conflicts)


def known_share(grid: OccupancyGrid, back_m: float = 0.15) -> Callable[[F64, F64], float]:
    """A function of a scan's points (robot frame) and the pose placing them in ``grid``'s
    frame: the share of them whose near side the grid knows, that is, whose cell ``back_m``
    back along the beam, toward the sensor, the grid holds as free or occupied. A keyframe of
    another team whose scan sees walls this map saw only from behind (an office's rooms, a
    wall apart), or rooms it never looked into, cannot be matched against it, however right
    its placement: most of its points have nothing facing them to be matched with. The
    grid's masks are taken at the first call: a check whose keyframes all match needs none."""
    masks: list[NDArray[np.bool_]] = []

    def share(points: F64, T_map_robot: F64) -> float:
        if not masks:
            masks.append(grid.occupied_mask() | grid.free_mask())
        known = masks[0]
        h, w = known.shape
        if len(points) == 0 or not known.size:
            return 0.0
        r = np.hypot(points[:, 0], points[:, 1])
        front = points * (np.maximum(r - back_m, 0.0) / np.maximum(r, 1e-9))[:, None]
        ij = grid.cell_of(transform_points(T_map_robot, front))
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        return float(known[ij[inside, 1], ij[inside, 0]].sum()) / len(points)

    return share


def union_area_m2(grid_a: PlanningMap, grid_b: PlanningMap, T_ab: F64,
                  sample_m: float = 0.2) -> float:
    """The area both maps know together [m²] when grid b is moved into a's frame by
    ``T_ab``: a's explored cells, and b's that fall where a has explored nothing. b's cells
    are taken every ``sample_m`` along each axis, each standing for its block (a rigid move
    keeps the area): a large house's map in a few milliseconds, to a percent."""
    known_a = grid_a.free | grid_a.occupied
    step = max(1, round(sample_m / grid_b.geometry.resolution_m))
    rc = np.argwhere((grid_b.free | grid_b.occupied)[::step, ::step]) * step
    if not len(rc):
        return float(known_a.sum()) * grid_a.geometry.cell_area_m2
    at_a = transform_points(T_ab, grid_b.geometry.cell_to_world(rc))
    cell = grid_a.geometry.world_to_cell(at_a)
    inside = grid_a.geometry.contains(cell)
    new = int((~inside).sum()) + int((~known_a[cell[inside, 0], cell[inside, 1]]).sum())
    return float(known_a.sum()) * grid_a.geometry.cell_area_m2 + \
        new * step * step * grid_b.geometry.cell_area_m2


@dataclass(frozen=True)
class CrossMatch:
    """Keyframe kb of robot b matched against robot a's keyframes around it."""

    ka: int
    kb: int
    T_ka_kb: F64
    information: F64      # in kb's frame (the between factor's error space)
    inlier_fraction: float
    turn_rad: float = 0.0  # how far the match turned kb from where it was placed
    weak: bool = False     # degenerate, held along its weak direction (``hold_weak``)


def cross_matches(a: RobotSlam, b: RobotSlam, every: int = 4, radius_m: float = 5.0,
                  min_inlier_fraction: float = 0.5, max_correction_m: float = 0.5,
                  max_correction_rad: float = math.radians(5.0),
                  T_ab: F64 | None = None, tried: list[int] | None = None,
                  only: list[int] | None = None,
                  min_seen_fraction: float = 0.0,
                  known: Callable[[F64, F64], float] | None = None,
                  hold_weak: bool = False) -> list[CrossMatch]:
    """Scan-to-map matches of b's keyframes (every ``every``-th, or those in ``only``) against
    a's keyframes within ``radius_m``, both placed by the current joint estimate (or b's by
    ``T_ab``): the overlap of the two maps says how they fit together, far more precisely than
    tag sightings.
    Matches that moved the keyframe implausibly far, matched poorly or were degenerate are left
    out; ``tried[0]`` is increased for every keyframe that had a map to match against: with
    ``min_seen_fraction``, only for one whose points a's map shows, from the same side, in at
    least that share (``seen_fraction``), and whose match is not degenerate: a keyframe that
    could not pass even where the fit is perfect, or that sees one wall, along which no fit
    can be told from a misfit, is no test of it. With ``known`` (``known_share`` of a's map),
    a keyframe so placed whose points' near side a's map knows in less than
    ``min_inlier_fraction`` of them counts as tried only if it matches: it sees mostly what a
    never saw from its side, and its failing says nothing of the placement. With
    ``hold_weak``, a degenerate match is matched again held along its weak direction, and
    kept with no information along it (``_without``)."""
    from server.slam.frontend import icp_params, min_points
    from server.slam.icp import icp, translation_degeneracy
    from server.slam.keyframes import local_point_map

    if not a.keyframes or not b.keyframes:
        return []
    pa, pb = a.keyframe_poses(), b.keyframe_poses()
    if T_ab is not None:  # b's keyframes not yet in a's frame: place them by T_ab
        pb = np.array([compose(T_ab, P) for P in pb])
    params = icp_params(a.cfg.matcher)
    out: list[CrossMatch] = []
    last = len(b.keyframes) - 1
    picked = (sorted({*range(0, last, max(1, every)), last}) if only is None  # newest: the meeting
              else sorted(k for k in set(only) if 0 <= k <= last))
    for kb in picked:
        d = np.hypot(pa[:, 0] - pb[kb, 0], pa[:, 1] - pb[kb, 1])
        near = np.flatnonzero(d <= radius_m)
        scan = b.keyframes[kb].matchable
        if len(near) == 0 or len(scan) < min_points(scan, a.cfg.matcher):
            continue
        target = local_point_map([a.keyframes[i] for i in near], pa[near],
                                 a.cfg.local_map.voxel_m)
        if len(target) < a.cfg.matcher.min_points:
            continue
        if min_seen_fraction > 0 and seen_fraction(
                scan.points, scan.normals, target, pb[kb], max_correction_m,
                params.min_normal_cos) < min_seen_fraction:
            continue
        m = icp(scan.points, scan.normals, target, pb[kb], params)
        weak = None
        if hold_weak and m.degenerate_dir is not None and \
                m.inlier_fraction >= min_inlier_fraction:
            # one wall's or a corridor's match: matched again with the keyframe held where it
            # is placed along the weak direction, it still says where it is across and how
            # it is turned
            weak = np.array([*m.degenerate_dir, 0.0])
            m = icp(scan.points, scan.normals, target, pb[kb], params,
                    np.outer(weak, weak) / HELD_ALONG_SIGMA_M ** 2)
            # the direction again, at the pose it settled on (the first match's was taken
            # at the pose it was placed at, turned by the error it corrects)
            again = translation_degeneracy(m.information, 1.0)
            if again is not None:
                weak = np.array([*again, 0.0])
        shift = math.hypot(*(m.T_map_scan[:2] - pb[kb, :2]))
        turn = abs(wrap_angle(m.T_map_scan[2] - pb[kb, 2]))
        passed = (m.converged and (weak is not None or not m.degenerate)
                  and m.inlier_fraction >= min_inlier_fraction
                  and shift <= max_correction_m and turn <= max_correction_rad)
        if tried is not None and not (min_seen_fraction > 0 and m.degenerate) and (
                passed or known is None or known(scan.points, pb[kb]) >= min_inlier_fraction):
            tried[0] += 1
        if not passed:
            continue
        ka = int(near[np.argmin(d[near])])
        c, s = math.cos(m.T_map_scan[2]), math.sin(m.T_map_scan[2])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        info = m.information if weak is None else _without(m.information, weak)
        out.append(CrossMatch(ka, kb, between(pa[ka], m.T_map_scan),
                              R.T @ info @ R, m.inlier_fraction,
                              wrap_angle(m.T_map_scan[2] - pb[kb, 2]), weak is not None))
    return out


def _without(information: F64, weak: F64) -> F64:
    """``information`` (x, y, θ) with nothing known along the unit direction ``weak``
    (x, y, 0), but for a σ of ``UNKNOWN_ALONG_SIGMA_M`` that keeps it invertible: the match's
    position along it was the placement's, not the map's."""
    Q = np.eye(3) - np.outer(weak, weak)
    return Q @ information @ Q + np.outer(weak, weak) / UNKNOWN_ALONG_SIGMA_M ** 2


def seen_fraction(points: F64, normals: F64, target: PointMap, T_map_scan: F64,
                  radius_m: float, min_cos: float) -> float:
    """The share of a scan's points (placed at ``T_map_scan``) that have a point of ``target``
    within ``radius_m`` whose normal faces the same way (cosine at least ``min_cos``): what of
    the scan the target's map saw, and from the same side. A short sensor's view of the far
    face of a wall the other robot saw from its own side, or of a room it never looked into,
    has little of it, however well the maps fit."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n == 0 or len(target.points) == 0:
        return 0.0
    c, s = math.cos(T_map_scan[2]), math.sin(T_map_scan[2])
    R = np.array([[c, -s], [s, c]])
    p = np.asarray(points, np.float64) @ R.T + T_map_scan[:2]
    nr = np.asarray(normals, np.float64) @ R.T
    k = min(8, len(target.points))
    _, idx = cKDTree(target.points).query(p, k=k, distance_upper_bound=radius_m)
    idx = np.asarray(idx).reshape(n, k)
    found = idx < len(target.points)
    tn = np.vstack([target.normals, np.zeros((1, 2))])[np.where(found, idx, len(target.points))]
    cos = np.einsum("nkd,nd->nk", tn, nr)
    return float(np.count_nonzero((found & (cos >= min_cos)).any(axis=1))) / n


def wall_grid(slams: list[RobotSlam], turn_rad: float = 0.0) -> tuple[float, float]:
    """The direction (modulo 90°) [rad] of the walls the robots' keyframes saw, turned by
    ``turn_rad``, and how closely they keep to one square grid (the length of the mean of
    e^{4iθ} over their normals: 1 when every wall is on it, near 0 in a building without
    one)."""
    zs = []
    for slam in slams:
        if not slam.keyframes:
            continue
        for kf, P in zip(slam.keyframes, slam.keyframe_poses(), strict=True):
            n = kf.matchable.normals
            zs.append(np.exp(4j * (np.arctan2(n[:, 1], n[:, 0]) + P[2] + turn_rad)))
    if not zs:
        return 0.0, 0.0
    m = np.concatenate(zs).mean()
    return float(np.angle(m) / 4), float(abs(m))


def square_walls_agree(a: list[RobotSlam], b: list[RobotSlam], turn_rad: float,
                       max_deg: float, min_alignment: float) -> bool:
    """Whether b's walls, turned by ``turn_rad``, run along a's within ``max_deg`` (modulo
    90°), both maps' walls keeping to a square grid at least ``min_alignment``."""
    phi_a, s_a = wall_grid(a)
    phi_b, s_b = wall_grid(b, turn_rad)
    if min(s_a, s_b) < min_alignment:
        return False
    err = wrap_angle(4 * (phi_b - phi_a)) / 4
    return abs(math.degrees(err)) <= max_deg


def square_turn(a: list[RobotSlam], b: list[RobotSlam], rough_rad: float, max_dev_rad: float,
                min_alignment: float) -> float | None:
    """The turn from b's frame to a's that puts b's walls on a's square grid, nearest to
    ``rough_rad`` (None: farther than ``max_dev_rad``, which must stay under 45° for the
    answer to be the one, or either map's walls keep to no square grid)."""
    phi_a, s_a = wall_grid(a)
    phi_b, s_b = wall_grid(b, rough_rad)
    if min(s_a, s_b) < min_alignment:
        return None
    err = wrap_angle(4 * (phi_b - phi_a)) / 4
    return wrap_angle(rough_rad - err) if abs(err) <= max_dev_rad else None
