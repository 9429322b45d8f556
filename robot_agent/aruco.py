"""ArUco tags on other robots: detect markers, estimate their pose, locate the robot carrying them.

Steps for one grayscale frame:

1. ``cv2.aruco.ArucoDetector`` finds the markers (corners refined with ``cornerSubPix``); each
   corner is then re-estimated as the intersection of lines fitted to its two edges
   (``refine_corners``), which removes the bias of corner detectors at the marker's outer
   corners (about 0.25 px inwards here, 1 cm of range at 1.5 m).
2. ``cv2.solvePnPGeneric`` with ``SOLVEPNP_IPPE_SQUARE`` gives both planar-pose solutions of
   each marker; a solution is kept when its RMS reprojection error is below the limit and the
   tag stands upright (robots stand on the floor, tags are mounted vertically), and the one with
   the smaller error wins. When IPPE fails (it can return NaN) ``SOLVEPNP_SQPNP`` is tried.
3. The tag pose in the observer's base frame is ``T_base_tag = T_base_cam · T_cam_tag``. With
   the tag's outward normal at planar angle ψ and the face's yaw σ on its robot (schemas.tags),
   the observed robot's heading relative to the observer is ``ψ − σ`` and its centre is the tag
   centre moved ``mast_half_width`` back along the normal. Range and bearing are those of that
   centre in the observer's base frame.
4. Standard deviations grow with range r: ``σ_r = a + b r²``, ``σ_bearing = a + b r``,
   ``σ_yaw = a + b r²`` (a basic model: PnP depth error grows with r², angular error with r);
   when IPPE's mirrored solution fits almost as well, the yaw is ambiguous and its σ is raised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from schemas.se2 import wrap_angle
from schemas.tags import SIDE_YAW_RAD, CameraMount, Side, TagLayout

#: cos of the largest tilt between a tag's "up" axis and the camera's up that is accepted.
MIN_UPRIGHT = math.cos(math.radians(30.0))


@dataclass(frozen=True)
class SigmaModel:
    range_a_m: float = 0.01
    range_b_per_m: float = 0.01
    bearing_a_rad: float = 0.005
    bearing_b_rad_per_m: float = 0.002
    yaw_a_rad: float = 0.03
    yaw_b_rad_per_m2: float = 0.03
    #: IPPE's mirrored solution fitting within this factor of the best one makes the yaw
    #: ambiguous (common past ~3 m); its σ is then raised to ``ambiguous_sigma_yaw_rad``.
    ambiguous_ratio: float = 3.0
    ambiguous_sigma_yaw_rad: float = 1.5

    def sigmas(self, range_m: float) -> tuple[float, float, float]:
        """(σ_range [m], σ_bearing [rad], σ_yaw [rad]) at ``range_m``."""
        r = range_m
        return (self.range_a_m + self.range_b_per_m * r * r,
                self.bearing_a_rad + self.bearing_b_rad_per_m * r,
                self.yaw_a_rad + self.yaw_b_rad_per_m2 * r * r)


@dataclass(frozen=True)
class MarkerPose:
    tag_id: int
    corners_px: np.ndarray      # (4, 2) TL, TR, BR, BL
    T_camera_tag: np.ndarray    # 4x4
    reprojection_error_px: float
    ambiguity: float            # best / second-best PnP error; near 1 = yaw may be mirrored


@dataclass(frozen=True)
class Sighting:
    """Another robot located from one of its tags, in the observer's base frame."""

    tag_id: int
    robot_id: str
    side: Side
    range_m: float
    bearing_rad: float
    yaw_rad: float
    sigma_range_m: float
    sigma_bearing_rad: float
    sigma_yaw_rad: float
    reprojection_error_px: float


@dataclass(frozen=True)
class Detections:
    sightings: list[Sighting]
    rejected: list[tuple[int, str]]   # (tag id, reason)


class TagDetector:
    def __init__(self, layout: TagLayout, mount: CameraMount, sigma: SigmaModel | None = None,
                 max_reprojection_px: float = 2.0) -> None:
        self.layout = layout
        self.T_base_cam = mount.T_robot_camera()
        self.sigma = sigma or SigmaModel()
        self.max_reprojection_px = max_reprojection_px
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, layout.dictionary))
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = 4
        params.cornerRefinementMinAccuracy = 0.01
        # Two faces of one mast are often seen side by side; OpenCV's default (0.125) merges
        # such neighbours and drops one of them.
        params.minMarkerDistanceRate = 0.05
        self.detector = cv2.aruco.ArucoDetector(dictionary, params)
        self.object_points = layout.marker_corners_tag().astype(np.float64)
        self.cells = int(dictionary.markerSize) + 2  # bits plus the black border

    def markers(self, image: np.ndarray, K: np.ndarray,
                dist: np.ndarray | None = None) -> tuple[list[MarkerPose], list[tuple[int, str]]]:
        """Markers in a grayscale ``image`` with their poses; plus (id, reason) rejections."""
        dist = np.zeros(5) if dist is None else dist
        corners, ids, _ = self.detector.detectMarkers(image)
        found, rejected = [], []
        if ids is None:
            return found, rejected
        gray = image.astype(np.float32)
        for c, tag_id in zip(corners, np.asarray(ids).reshape(-1), strict=True):
            px = refine_corners(gray, np.asarray(c, np.float64).reshape(4, 2), self.cells)
            pose = self._solve(px, K, dist)
            if pose is None:
                rejected.append((int(tag_id), "no upright pose within the reprojection limit"))
                continue
            found.append(MarkerPose(int(tag_id), px, *pose))
        return found, rejected

    def _solve(self, px: np.ndarray, K: np.ndarray, dist: np.ndarray
               ) -> tuple[np.ndarray, float, float] | None:
        """(T_camera_tag, RMS error [px], ambiguity) of the best upright solution; ambiguity is
        the best error over the other solution's (near 1: the two poses fit equally well)."""
        for method in (cv2.SOLVEPNP_IPPE_SQUARE, cv2.SOLVEPNP_SQPNP):
            try:
                n, rvecs, tvecs, errs = cv2.solvePnPGeneric(self.object_points, px, K, dist,
                                                            flags=method)
            except cv2.error:
                continue
            errors = np.asarray(errs, float).reshape(-1) if errs is not None else np.full(n, 1e9)
            found: list[tuple[float, np.ndarray]] = []
            for i in range(n):
                rvec, tvec = np.asarray(rvecs[i], float), np.asarray(tvecs[i], float).reshape(3)
                err = float(errors[i])
                if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))
                        and math.isfinite(err)) or tvec[2] <= 0:
                    continue
                R, _ = cv2.Rodrigues(rvec)
                if -R[1, 1] < MIN_UPRIGHT:  # tag "up" far from the camera's up: not a robot tag
                    continue
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, tvec
                found.append((err, T))
            found.sort(key=lambda f: f[0])
            if found and found[0][0] <= self.max_reprojection_px:
                other = [e for e in errors if math.isfinite(e)]
                second = sorted(other)[1] if len(other) > 1 else math.inf
                ambiguity = found[0][0] / second if second > 0 else 1.0
                return found[0][1], found[0][0], min(ambiguity, 1.0)
        return None

    def detect(self, image: np.ndarray, K: np.ndarray, observer_id: str,
               dist: np.ndarray | None = None) -> Detections:
        """Robots seen in ``image`` by ``observer_id``; own and unknown tags are rejected."""
        poses, rejected = self.markers(image, K, dist)
        sightings = []
        for m in poses:
            owner = self.layout.owner(m.tag_id)
            if owner is None:
                rejected.append((m.tag_id, "tag belongs to no robot"))
                continue
            robot_id, side = owner
            if robot_id == observer_id:
                rejected.append((m.tag_id, "own tag"))
                continue
            sightings.append(self.locate(m, robot_id, side))
        return Detections(sightings, rejected)

    def locate(self, m: MarkerPose, robot_id: str, side: Side) -> Sighting:
        """The robot carrying marker ``m`` on ``side``, in the observer's base frame."""
        T_base_tag = self.T_base_cam @ m.T_camera_tag
        normal = T_base_tag[:3, 2]
        psi = math.atan2(normal[1], normal[0])
        h = self.layout.mast_half_width_m
        x = T_base_tag[0, 3] - h * math.cos(psi)
        y = T_base_tag[1, 3] - h * math.sin(psi)
        rng = math.hypot(x, y)
        yaw = wrap_angle(psi - SIDE_YAW_RAD[side])
        s_r, s_b, s_y = self.sigma.sigmas(rng)
        if m.ambiguity > 1.0 / self.sigma.ambiguous_ratio:
            s_y = max(s_y, self.sigma.ambiguous_sigma_yaw_rad)
        return Sighting(m.tag_id, robot_id, side, rng, math.atan2(y, x), yaw, s_r, s_b, s_y,
                        m.reprojection_error_px)


def refine_corners(gray: np.ndarray, quad: np.ndarray, cells: int,
                   min_cell_px: float = 3.0) -> np.ndarray:
    """Corners of a dark square on a bright surround as intersections of fitted edge lines.

    Along each edge, intensity profiles are sampled across the edge (bilinear, ¼ px steps)
    within the black border's width ``w``. For a blurred step from dark level ``d`` to bright
    level ``b`` the edge's offset is ``e = o_max − ∫ (I(o) − d) / (b − d) do`` over
    ``o ∈ [−w, w]``, which holds for any symmetric blur. A total-least-squares line through the
    edge points of each side gives the corners by intersection. Markers with cells smaller
    than ``min_cell_px`` keep their detected corners; so does a side with too few good samples.
    """
    q = np.asarray(quad, np.float64)
    perimeter = float(np.linalg.norm(np.roll(q, -1, axis=0) - q, axis=1).sum())
    cell_px = perimeter / 4 / cells
    if cell_px < min_cell_px:
        return q
    centre = q.mean(axis=0)
    half = min(0.45 * cell_px, 4.0)
    offsets = np.arange(-half, half + 1e-9, 0.25)
    lines = []
    for k in range(4):
        a, b = q[k], q[(k + 1) % 4]
        length = float(np.linalg.norm(b - a))
        t = (b - a) / length
        n = np.array([-t[1], t[0]])
        if float(n @ (a - centre)) < 0:
            n = -n                                       # outward: towards the bright side
        s = np.linspace(0.15, 0.85, max(int(length * 0.7), 4))
        pts = a + s[:, None] * (b - a)
        xy = pts[:, None, :] + offsets[None, :, None] * n
        prof = cv2.remap(gray, xy[..., 0].astype(np.float32), xy[..., 1].astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        dark, bright = prof[:, :2].mean(axis=1), prof[:, -2:].mean(axis=1)
        contrast = bright - dark
        good = contrast > 20.0
        if good.sum() < 3:
            return q
        norm = (prof[good] - dark[good, None]) / contrast[good, None]
        area = np.sum((norm[:, 1:] + norm[:, :-1]) * 0.5 * np.diff(offsets), axis=1)
        e = offsets[-1] - area
        edge = pts[good] + e[:, None] * n
        mean = edge.mean(axis=0)
        _, _, vt = np.linalg.svd(edge - mean)
        lines.append((mean, vt[0]))
    out = np.empty_like(q)
    for k in range(4):
        (p1, d1), (p2, d2) = lines[k - 1], lines[k]   # corner k ends edge k-1, starts edge k
        A = np.column_stack([d1, -d2])
        if abs(np.linalg.det(A)) < 1e-9:
            return q
        u = np.linalg.solve(A, p2 - p1)
        out[k] = p1 + u[0] * d1
    if np.max(np.linalg.norm(out - q, axis=1)) > max(2.0, cell_px):
        return q  # refinement went astray; keep the detector's corners
    return out


def in_line_of_sight(range_m: float, bearing_rad: float, ranges_m: np.ndarray,
                     angles_rad: np.ndarray, half_width_rad: float = math.radians(3.0),
                     margin_m: float = 0.4) -> bool:
    """The dissertation's check against the LIDAR: a sighting at (range, bearing) is false when
    the scan has a return clearly closer (by more than ``margin_m``, which covers the observed
    robot's own body) within ``half_width_rad`` of the bearing — a wall stands in between and
    the tag was seen through a gap or is not what it seems. Beams without a return (inf/NaN)
    never object."""
    r = np.asarray(ranges_m, dtype=np.float64)
    a = np.asarray(angles_rad, dtype=np.float64)
    off = np.abs(wrap_angle(a - bearing_rad))
    near = (off <= half_width_rad) & np.isfinite(r)
    return not bool(np.any(r[near] < range_m - margin_m))


@dataclass(frozen=True)
class LidarFix:
    """The observed robot's centre from the LIDAR returns off its body."""

    range_m: float
    bearing_rad: float
    sigma_range_m: float
    sigma_bearing_rad: float
    beams: int
    rms_m: float


def lidar_fix(range_m: float, bearing_rad: float, ranges_m: np.ndarray, angles_rad: np.ndarray,
              body_radius_m: float, sigma_m: float = 0.01, floor_m: float = 0.02,
              across_tolerance_m: float = 0.2, min_beams: int = 2) -> LidarFix | None:
    """Range and bearing of a robot seen at (``range_m``, ``bearing_rad``) by its tag, from
    the scan: past a couple of metres a tag's range is biased (the marker is a few pixels
    wide) and its centre is off by up to the mast's width across the line of sight (the
    tag's heading is unreliable), while the LIDAR hits the robot's round body to the
    centimetre. The returns near the tag's bearing that lie where the body's front should be
    (within a tolerance that grows with range) are fitted with a circle of the body's radius.

    None when fewer than ``min_beams`` returns fit, when the circle does not fit them
    (residual over 3σ), or when the fitted centre is farther than ``across_tolerance_m``
    across the line of sight from the tag's: then the tag saw something the LIDAR does not
    confirm, and its own estimate stands. σ: from the fit, floored at ``floor_m`` (body
    shape, the scan's timing)."""
    rho = float(body_radius_m)
    if rho <= 0 or not (math.isfinite(range_m) and math.isfinite(bearing_rad)) or range_m <= rho:
        return None
    r = np.asarray(ranges_m, dtype=np.float64)
    a = np.asarray(angles_rad, dtype=np.float64)
    along = 0.1 + 0.15 * range_m                      # covers the tag's range bias
    half = math.atan2(rho + across_tolerance_m, range_m)
    off = wrap_angle(a - bearing_rad)
    front = range_m - rho
    sel = (np.abs(off) <= half) & np.isfinite(r) & (np.abs(r - front) <= along)
    if sel.sum() < min_beams:
        return None
    r, a = r[sel], a[sel]
    keep = r <= r.min() + rho                         # one body: its returns span ≤ ρ in depth
    r, a = r[keep], a[keep]
    if len(r) < min_beams:
        return None
    pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    u = pts.mean(axis=0) / np.linalg.norm(pts.mean(axis=0))
    c = pts.mean(axis=0) + rho * u                    # start on the far side of the returns
    J = np.zeros((len(pts), 2))
    for _ in range(20):
        d = c - pts
        n = np.linalg.norm(d, axis=1)
        if np.any(n < 1e-9):
            return None
        res = n - rho
        J = d / n[:, None]
        step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        c = c + step
        if np.linalg.norm(step) < 1e-6:
            break
    n = np.linalg.norm(c - pts, axis=1)
    rms = float(np.sqrt(np.mean((n - rho) ** 2)))
    if rms > 3 * sigma_m or float(np.dot(c - pts.mean(axis=0), u)) <= 0:
        return None
    rng, brg = float(np.hypot(*c)), float(math.atan2(c[1], c[0]))
    if abs(rng - range_m) > along or abs(wrap_angle(brg - bearing_rad)) * \
            range_m > across_tolerance_m + 0.1 * rho:
        return None
    JtJ = J.T @ J
    if np.linalg.cond(JtJ) > 1e8:
        return None
    cov = np.linalg.inv(JtJ) * sigma_m ** 2
    radial = c / rng
    tangential = np.array([-radial[1], radial[0]])
    s_r = math.hypot(math.sqrt(max(float(radial @ cov @ radial), 0.0)), floor_m)
    s_t = math.hypot(math.sqrt(max(float(tangential @ cov @ tangential), 0.0)), floor_m)
    return LidarFix(rng, brg, s_r, s_t / rng, len(pts), rms)
