"""Where the fiducial tags and the camera sit on a robot: one contract for simulator and agent.

Every robot carries a square mast centred on its base with one ArUco marker on each of its four
faces (front, left, back, right). The simulator draws the markers from this layout; the agent's
detector uses the same layout to turn a marker's pose into the pose of the robot carrying it.

Frames (all right-handed, metres):

- robot base: x forward, y left, z up, origin on the floor under the robot's centre.
- tag: origin at the marker's centre, z out of the face (away from the robot), y up, x to the
  right of a viewer who faces the marker. The marker corners in this frame, in ArUco's order
  (top-left, top-right, bottom-right, bottom-left), are ``(∓s/2, ±s/2, 0)`` with ``s`` the marker
  size, which is the object-point convention of ``cv2.SOLVEPNP_IPPE_SQUARE``.
- camera (optical): z along the optical axis, x right, y down (OpenCV).

Tag ids: robot ``r<N>`` (N >= 1) owns ids ``4(N-1) .. 4(N-1)+3`` (front, left, back, right),
so DICT_4X4_50 serves robots r1..r12. Robots with other ids need an entry in ``first_ids``
(robot id -> id of its front tag); do not mix the two schemes within one id range.
"""

from __future__ import annotations

import itertools
import math
import re
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from schemas.config import ConfigModel

Side = Literal["front", "left", "back", "right"]
SIDES: tuple[Side, ...] = ("front", "left", "back", "right")
#: Yaw of each face's outward normal in the robot base frame [rad].
SIDE_YAW_RAD: dict[Side, float] = {
    "front": 0.0, "left": math.pi / 2, "back": math.pi, "right": -math.pi / 2}
_RN = re.compile(r"^r([1-9][0-9]*)$")


class TagLayoutError(ValueError):
    """A robot has no tag ids under the layout, or a tag id belongs to no robot."""

    user_error = True


class TagLayout(ConfigModel):
    """Marker dictionary, size and mounting shared by every robot."""

    dictionary: str = Field(
        "DICT_4X4_50", pattern=r"^DICT_[A-Z0-9_]+$", description="OpenCV ArUco dictionary of the "
        "markers")
    marker_size_m: float = Field(0.12, gt=0.0, le=2.0,
                                 description="edge of the marker's black square [m]")
    plate_size_m: float = Field(0.16, gt=0.0, le=2.0,
                                description="edge of the white face around the marker [m]")
    mast_half_width_m: float = Field(0.08, gt=0.0, le=2.0,
                                     description="robot centre to each face [m]")
    centre_height_m: float = Field(0.30, gt=0.0, le=5.0,
                                   description="height of the marker centres [m]")
    first_ids: dict[str, int] = Field(default_factory=dict,
                                      description="robot id -> id of its front tag")

    @model_validator(mode="after")
    def _check(self) -> TagLayout:
        if self.plate_size_m < self.marker_size_m:
            raise ValueError("plate_size_m must be >= marker_size_m (the white quiet zone)")
        if self.plate_size_m > 2 * self.mast_half_width_m + 1e-9:
            raise ValueError("plate_size_m must fit the mast face (<= 2 * mast_half_width_m)")
        starts = sorted(self.first_ids.values())
        if any(b - a < len(SIDES) for a, b in itertools.pairwise(starts)):
            raise ValueError("first_ids overlap: each robot needs 4 consecutive ids")
        return self

    # -- ids --------------------------------------------------------------------------------
    def first_id(self, robot_id: str) -> int:
        if robot_id in self.first_ids:
            return self.first_ids[robot_id]
        m = _RN.match(robot_id)
        if m is None:
            raise TagLayoutError(f"robot {robot_id!r} has no tag ids: name it r<N> or add it "
                                 "to tags.first_ids")
        return len(SIDES) * (int(m.group(1)) - 1)

    def tag_id(self, robot_id: str, side: Side) -> int:
        return self.first_id(robot_id) + SIDES.index(side)

    def owner(self, tag_id: int) -> tuple[str, Side] | None:
        """The robot and face carrying ``tag_id``, or None when no robot owns it."""
        if tag_id < 0:
            return None
        for rid, first in self.first_ids.items():
            if first <= tag_id < first + len(SIDES):
                return rid, SIDES[tag_id - first]
        return f"r{tag_id // len(SIDES) + 1}", SIDES[tag_id % len(SIDES)]

    # -- geometry ---------------------------------------------------------------------------
    def T_robot_tag(self, side: Side) -> np.ndarray:
        """4x4 transform of the tag frame on ``side`` into the robot base frame."""
        yaw = SIDE_YAW_RAD[side]
        c, s = math.cos(yaw), math.sin(yaw)
        z_axis = np.array([c, s, 0.0])          # outward normal
        y_axis = np.array([0.0, 0.0, 1.0])      # up
        x_axis = np.cross(y_axis, z_axis)       # viewer's right
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2] = x_axis, y_axis, z_axis
        T[:3, 3] = (self.mast_half_width_m * c, self.mast_half_width_m * s,
                    self.centre_height_m)
        return T

    def marker_corners_tag(self) -> np.ndarray:
        """(4, 3) marker corners in the tag frame, ArUco order TL, TR, BR, BL [m]."""
        return square_corners(self.marker_size_m)

    def plate_corners_tag(self) -> np.ndarray:
        """(4, 3) corners of the white plate in the tag frame, same order [m]."""
        return square_corners(self.plate_size_m)


def square_corners(size_m: float) -> np.ndarray:
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


#: Rotation taking optical-frame vectors (z forward, x right, y down) into a frame that looks
#: along +x with z up (x_body = z_opt, y_body = -x_opt, z_body = -y_opt).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class CameraMount(ConfigModel):
    """Pose of the forward camera on the robot (optical axis horizontal, ``yaw_rad`` off x)."""

    x_m: float = Field(0.12, ge=-2.0, le=2.0, description="camera forward of the robot's centre")
    y_m: float = Field(0.0, ge=-2.0, le=2.0, description="camera left of the robot's centre")
    z_m: float = Field(0.30, gt=0.0, le=5.0, description="camera height above the floor")
    yaw_rad: float = Field(
        0.0, ge=-math.pi, le=math.pi, description="camera's optical axis, counter-clockwise from "
        "the robot's forward axis")

    def T_robot_camera(self) -> np.ndarray:
        """4x4 transform of the optical frame into the robot base frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        R_robot_body = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T = np.eye(4)
        T[:3, :3] = R_robot_body @ R_BODY_OPTICAL
        T[:3, 3] = (self.x_m, self.y_m, self.z_m)
        return T
