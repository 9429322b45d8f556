"""Camera and tags: rendered images go through the agent's real OpenCV detector."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot_agent.aruco import TagDetector
from schemas.se2 import wrap_angle
from schemas.tags import SIDES, CameraMount, TagLayout, TagLayoutError
from sim.simulator import SimParams, Simulator
from sim.world import World

LAYOUT, MOUNT = TagLayout(), CameraMount()


def empty() -> World:
    return World.from_shapes("empty", "test", [np.array([[50, 50], [51, 50], [51, 51],
                                                         [50, 51.0]])], [])


def facing_pose(distance_m: float, bearing: float, turn: float) -> tuple[float, float, float]:
    """Pose of r2 whose front tag centre is ``distance_m`` from r1's camera (r1 at the origin,
    heading 0) at ``bearing``, its face turned ``turn`` away from looking straight back."""
    cam = MOUNT.x_m
    tx, ty = cam + distance_m * math.cos(bearing), distance_m * math.sin(bearing)
    heading = bearing + math.pi + turn
    h = LAYOUT.mast_half_width_m
    return tx + h * math.cos(heading), ty + h * math.sin(heading), wrap_angle(heading)


def test_tag_at_1_5_m_is_detected_within_2_cm_and_half_a_degree() -> None:
    detector = TagDetector(LAYOUT, MOUNT)
    rng = np.random.default_rng(2)
    checked = 0
    for k in range(12):
        pose = facing_pose(1.5, rng.uniform(-0.4, 0.4), rng.uniform(-0.8, 0.8))
        sim = Simulator(empty(), {"r1": (0.0, 0.0, 0.0), "r2": pose}, SimParams(), seed=k)
        frame = sim.sense().frames["r1"]
        assert frame.image.shape == (480, 640) and frame.image.dtype == np.uint8
        (observed, tag_id, rel) = frame.relatives[0]
        assert (observed, tag_id) == ("r2", LAYOUT.tag_id("r2", "front"))
        found = detector.detect(frame.image, sim.p.camera.camera.K, "r1")
        s = next(s for s in found.sightings if s.tag_id == tag_id)
        assert s.robot_id == "r2" and s.side == "front"
        assert abs(s.range_m - math.hypot(rel[0], rel[1])) <= 0.02
        assert abs(math.degrees(s.bearing_rad - math.atan2(rel[1], rel[0]))) <= 0.5
        assert abs(math.degrees(wrap_angle(s.yaw_rad - rel[2]))) < 5.0
        assert s.sigma_range_m > 0 and s.sigma_yaw_rad > s.sigma_bearing_rad > 0
        checked += 1
    assert checked == 12


def test_a_tag_behind_a_wall_is_never_rendered() -> None:
    wall = np.array([[1.2, -1.0], [1.3, -1.0], [1.3, 1.0], [1.2, 1.0]])
    walled = World.from_shapes("wall", "test", [wall], [])
    rng = np.random.default_rng(4)
    rendered_without_wall = 0
    for k in range(30):
        pose = facing_pose(rng.uniform(1.6, 3.0), rng.uniform(-0.3, 0.3), rng.uniform(-0.6, 0.6))
        spawn = {"r1": (0.0, 0.0, 0.0), "r2": pose}
        assert "r1" not in Simulator(walled, spawn, SimParams(), seed=k).sense().frames
        rendered_without_wall += "r1" in Simulator(empty(), spawn, SimParams(), seed=k
                                                   ).sense().frames
    assert rendered_without_wall == 30  # the same views are rendered when nothing is between


def test_a_third_robot_occludes_and_back_faces_and_far_tags_are_not_rendered() -> None:
    front = facing_pose(2.0, 0.0, 0.0)
    sim = Simulator(empty(), {"r1": (0, 0, 0), "r2": front, "r3": (1.0, 0.0, 0.0)},
                    SimParams(), seed=0)
    frames = sim.sense().frames
    assert "r1" in frames and {o for o, _, _ in frames["r1"].relatives} == {"r3"}
    away = (front[0], front[1], 0.0)      # r2 turned around: r1 sees its back tag
    sim = Simulator(empty(), {"r1": (0, 0, 0), "r2": away}, SimParams(), seed=0)
    (view,) = sim.sense().frames["r1"].views
    assert view.side == "back"
    far = facing_pose(8.0, 0.0, 0.0)
    assert not Simulator(empty(), {"r1": (0, 0, 0), "r2": far}, SimParams()).sense().frames


def test_tag_layout_ids_round_trip_and_geometry() -> None:
    ids = {LAYOUT.tag_id(f"r{n}", side) for n in range(1, 13) for side in SIDES}
    assert ids == set(range(48))
    for n in range(1, 13):
        for side in SIDES:
            assert LAYOUT.owner(LAYOUT.tag_id(f"r{n}", side)) == (f"r{n}", side)
    custom = TagLayout(first_ids={"alpha": 20})
    assert custom.tag_id("alpha", "back") == 22 and custom.owner(22) == ("alpha", "back")
    with pytest.raises(TagLayoutError):
        LAYOUT.tag_id("alpha", "front")
    with pytest.raises(ValueError):
        TagLayout(first_ids={"a": 0, "b": 2})
    T = LAYOUT.T_robot_tag("left")  # normal along +y, "up" along +z, right-handed
    assert np.allclose(T[:3, 2], [0, 1, 0]) and np.allclose(T[:3, 1], [0, 0, 1])
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    C = MOUNT.T_robot_camera()  # optical axis forward, image x to the right
    assert np.allclose(C[:3, 2], [1, 0, 0]) and np.allclose(C[:3, 0], [0, -1, 0])


def test_spurious_views_are_drawn_false_and_flagged() -> None:
    """With every view falsified, what the detector reads disagrees with the truth, and the
    frame says how each false tag was made."""
    from dataclasses import replace

    detector = TagDetector(LAYOUT, MOUNT)
    params = SimParams()
    params = replace(params, camera=replace(params.camera, spurious_rate=1.0))
    kinds: set[str] = set()
    wrong = 0
    for k in range(20):
        spawn = {"r1": (0.0, 0.0, 0.0), "r2": facing_pose(2.0, 0.1, 0.2), "r3": (-3.0, 3.0, 0.0)}
        frame = Simulator(empty(), spawn, params, seed=k).sense().frames.get("r1")
        if frame is None:
            continue
        kinds |= set(frame.spurious.values())
        for s in detector.detect(frame.image, params.camera.camera.K, "r1").sightings:
            rel = next(r for o, _, r in frame.relatives if o == "r2")
            far = math.hypot(s.range_m * math.cos(s.bearing_rad) - rel[0],
                             s.range_m * math.sin(s.bearing_rad) - rel[1]) > 0.5
            turned = abs(wrap_angle(s.yaw_rad - rel[2])) > 0.4
            wrong += s.robot_id != "r2" or far or turned
    assert {"id", "pose"} <= kinds
    assert wrong >= 10
