"""The forward camera: which tags it sees, and a grayscale image of them in perspective.

A tag is seen when its face points towards the camera, its four plate corners project inside
the image in front of the camera, its centre is within ``max_range_m``, and the straight lines
from the camera to its centre and to both vertical edges are not blocked (by walls in the LIDAR
plane or by a third robot). Occlusion is decided in the plane: walls and doors are taller than
the tags, so a blocked line in the plane is blocked at tag height too.

Each visible plate (white square with the ArUco marker) is drawn by the homography of its plane
(``cv2.getPerspectiveTransform`` of the four projected corners, ``cv2.warpPerspective``),
supersampled and area-averaged so that edges are anti-aliased, farthest first. The frame is then
blurred (Gaussian) and given pixel noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from schemas.se2 import wrap_angle
from schemas.tags import SIDES, CameraMount, Side, TagLayout
from sim.geometry import inverse, planar_transform

BACKGROUND, PLATE, INK = 110.0, 225.0, 25.0
_PX_PER_CELL = 24
_SUPERSAMPLE = 4


@dataclass(frozen=True)
class PinholeCamera:
    width: int = 640
    height: int = 480
    fx: float = 554.2562584220408   # 60° horizontal field of view at 640 px
    fy: float = 554.2562584220408
    cx: float = 319.5
    cy: float = 239.5

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_rad: float) -> PinholeCamera:
        f = (width / 2) / math.tan(hfov_rad / 2)
        return cls(width, height, f, f, (width - 1) / 2, (height - 1) / 2)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """(N, 3) optical-frame points -> (N, 2) pixels (u right, v down)."""
        z = p_cam[:, 2]
        return np.column_stack([self.fx * p_cam[:, 0] / z + self.cx,
                                self.fy * p_cam[:, 1] / z + self.cy])


@dataclass(frozen=True)
class TagView:
    """One tag as the camera of ``observer`` sees it."""

    observer: str
    observed: str
    side: Side
    tag_id: int
    plate_px: np.ndarray      # (4, 2) projected plate corners TL, TR, BR, BL
    T_camera_tag: np.ndarray  # 4x4
    distance_m: float


Blocked = Callable[[tuple[float, float], tuple[float, float], str, str], bool]


def visible_tags(observer: str, poses: dict[str, tuple[float, float, float]],
                 layout: TagLayout, mount: CameraMount, camera: PinholeCamera,
                 max_range_m: float, min_facing_cos: float, blocked: Blocked) -> list[TagView]:
    """Tags of the other robots that the observer's camera sees, nearest first.

    ``blocked(p, q, observer, observed)`` says whether the planar line p -> q is obstructed.
    """
    T_world_cam = planar_transform(poses[observer]) @ mount.T_robot_camera()
    T_cam_world = inverse(T_world_cam)
    cam_xy = (float(T_world_cam[0, 3]), float(T_world_cam[1, 3]))
    axis = math.atan2(T_world_cam[1, 2], T_world_cam[0, 2])   # optical axis in the plane
    half_fov = math.atan2(camera.width / 2, camera.fx)
    frames = _tag_frames(layout)
    reach = layout.mast_half_width_m + layout.plate_size_m
    plate = np.hstack([layout.plate_corners_tag(), np.ones((4, 1))])
    views = []
    for rid, pose in poses.items():
        if rid == observer:
            continue
        # cheap tests on the robot's centre first: in range, and inside the field of view
        d = math.hypot(pose[0] - cam_xy[0], pose[1] - cam_xy[1])
        if d > max_range_m + reach:
            continue
        off = abs(wrap_angle(math.atan2(pose[1] - cam_xy[1], pose[0] - cam_xy[0]) - axis))
        if d > reach and off > half_fov + math.asin(min(1.0, reach / d)):
            continue
        T_world_robot = planar_transform(pose)
        for side in SIDES:
            T_world_tag = T_world_robot @ frames[side]
            centre = T_world_tag[:3, 3]
            to_cam = np.array([cam_xy[0], cam_xy[1], T_world_cam[2, 3]]) - centre
            dist = float(np.linalg.norm(to_cam))
            if not 1e-6 < dist <= max_range_m:
                continue
            if float(T_world_tag[:3, 2] @ to_cam) / dist < min_facing_cos:
                continue
            T_cam_tag = T_cam_world @ T_world_tag
            corners_cam = (T_cam_tag @ plate.T).T[:, :3]
            if np.any(corners_cam[:, 2] < 0.05):
                continue
            px = camera.project(corners_cam)
            if (px[:, 0].min() < 0 or px[:, 1].min() < 0 or px[:, 0].max() > camera.width - 1
                    or px[:, 1].max() > camera.height - 1):
                continue
            corners_world = (T_world_tag @ plate.T).T
            targets = [(float(centre[0]), float(centre[1])),
                       (float(corners_world[0, 0]), float(corners_world[0, 1])),
                       (float(corners_world[1, 0]), float(corners_world[1, 1]))]
            if any(blocked(cam_xy, t, observer, rid) for t in targets):
                continue
            views.append(TagView(observer, rid, side, layout.tag_id(rid, side), px, T_cam_tag,
                                 dist))
    return sorted(views, key=lambda v: v.distance_m)


_FRAMES: dict[tuple[float, float], dict[Side, np.ndarray]] = {}


def _tag_frames(layout: TagLayout) -> dict[Side, np.ndarray]:
    """``T_robot_tag`` of every side, computed once per mounting."""
    key = (layout.mast_half_width_m, layout.centre_height_m)
    frames = _FRAMES.get(key)
    if frames is None:
        frames = _FRAMES[key] = {side: layout.T_robot_tag(side) for side in SIDES}
    return frames


class TagRenderer:
    """Draws plates with their markers; marker textures are made once per id."""

    def __init__(self, layout: TagLayout, camera: PinholeCamera) -> None:
        self.layout = layout
        self.camera = camera
        self.dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, layout.dictionary))
        self._textures: dict[int, np.ndarray] = {}

    def texture(self, tag_id: int) -> np.ndarray:
        """Plate texture (float32): white plate, marker of 6 cells (4x4 bits + border)."""
        tex = self._textures.get(tag_id)
        if tex is None:
            cells = int(self.dictionary.markerSize) + 2
            cell_m = self.layout.marker_size_m / cells
            marker = cv2.aruco.generateImageMarker(self.dictionary, tag_id,
                                                   cells * _PX_PER_CELL, borderBits=1)
            side = round(self.layout.plate_size_m / cell_m * _PX_PER_CELL)
            off = (side - marker.shape[0]) // 2
            tex = np.full((side, side), PLATE, np.float32)
            tex[off:off + marker.shape[0], off:off + marker.shape[1]] = np.where(
                marker > 127, PLATE, INK)
            self._textures[tag_id] = tex
        return tex

    def render(self, views: list[TagView], rng: np.random.Generator, blur_sigma_px: float,
               noise_sigma: float) -> np.ndarray:
        cam = self.camera
        img = np.full((cam.height, cam.width), BACKGROUND, np.float32)
        img += np.linspace(-12.0, 12.0, cam.height, dtype=np.float32)[:, None]  # soft shading
        for view in sorted(views, key=lambda v: -v.distance_m):
            self._draw(img, view)
        if blur_sigma_px > 0:
            img = np.asarray(cv2.GaussianBlur(img, (0, 0), blur_sigma_px), np.float32)
        if noise_sigma > 0:
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def _draw(self, img: np.ndarray, view: TagView) -> None:
        tex = self.texture(view.tag_id)
        k = _SUPERSAMPLE
        px = view.plate_px
        u0, v0 = math.floor(px[:, 0].min()) - 1, math.floor(px[:, 1].min()) - 1
        u1, v1 = math.ceil(px[:, 0].max()) + 2, math.ceil(px[:, 1].max()) + 2
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, img.shape[1]), min(v1, img.shape[0])
        if u1 <= u0 or v1 <= v0:
            return
        # output pixel u spans [u - 0.5, u + 0.5); sub-pixel j of the ROI is centred on
        # u0 - 0.5 + (j + 0.5) / k, so u maps to j = (u - u0 + 0.5) k - 0.5
        dst = ((px - (u0, v0) + 0.5) * k - 0.5).astype(np.float32)
        s = tex.shape[0]
        src = np.array([[-0.5, -0.5], [s - 0.5, -0.5], [s - 0.5, s - 0.5], [-0.5, s - 0.5]],
                       np.float32)
        H = cv2.getPerspectiveTransform(src, dst)
        size = ((u1 - u0) * k, (v1 - v0) * k)
        colour = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        cover = cv2.warpPerspective(np.ones_like(tex), H, size, flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        colour = cv2.resize(colour, (u1 - u0, v1 - v0), interpolation=cv2.INTER_AREA)
        alpha = cv2.resize(cover, (u1 - u0, v1 - v0), interpolation=cv2.INTER_AREA)
        roi = img[v0:v1, u0:u1]
        roi *= 1.0 - alpha
        roi += colour
