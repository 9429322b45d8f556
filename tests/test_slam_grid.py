"""Occupancy grid and map export: a known room, nav2 files, PLY, incremental vs re-rendered."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from server.slam.export import nav2_image, read_ply_xy, write_nav2, write_ply
from server.slam.grid import GridParams, OccupancyGrid
from server.slam.keyframes import Keyframe
from server.slam.mapping import GridMapper, point_cloud, render_grid
from server.slam.scan import scan_to_points
from tests.test_slam_synthetic import box, cast

ROOM = (0.01, 0.02, 6.03, 4.04)  # walls off the cell boundaries
ANGLES = -math.pi + 2 * math.pi * np.arange(720) / 720
POSES = np.array([[1.5, 1.0, 0.0], [4.5, 1.2, 1.0], [3.0, 3.0, -2.0], [1.0, 3.2, 0.5]])


def room_keyframes(poses: np.ndarray = POSES) -> list[Keyframe]:
    walls = box(*ROOM)
    out = []
    for i, T in enumerate(poses):
        sc = scan_to_points(cast(walls, T, ANGLES), ANGLES, 0.05, 30.0)
        out.append(Keyframe.create(i, i, sc, T))
    return out


def cell_centres(grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray]:
    h, w = grid.shape
    xs = grid.origin[0] + (np.arange(w) + 0.5) * grid.resolution_m
    ys = grid.origin[1] + (np.arange(h) + 0.5) * grid.resolution_m
    return np.meshgrid(xs, ys)  # row index = y, column index = x


def test_free_and_occupied_cells_match_a_known_room() -> None:
    params = GridParams(resolution_m=0.05)
    grid = render_grid(params, room_keyframes(), POSES)
    xs, ys = cell_centres(grid)
    x0, y0, x1, y1 = ROOM
    margin = 2 * params.resolution_m
    inside = (xs > x0 + margin) & (xs < x1 - margin) & (ys > y0 + margin) & (ys < y1 - margin)
    d_wall = np.minimum.reduce([np.abs(xs - x0), np.abs(xs - x1), np.abs(ys - y0), np.abs(ys - y1)])
    on_wall = (d_wall < 0.5 * params.resolution_m) & (xs > x0 - 0.01) & (xs < x1 + 0.01) & \
        (ys > y0 - 0.01) & (ys < y1 + 0.01)
    outside = (xs < x0 - margin) | (xs > x1 + margin) | (ys < y0 - margin) | (ys > y1 + margin)
    free, occ = grid.free_mask(), grid.occupied_mask()
    assert free[inside].mean() > 0.99
    assert not occ[inside].any()
    assert occ[on_wall].mean() > 0.95
    nav = grid.to_nav2()
    assert nav.dtype == np.int8
    assert (nav[outside] == -1).all()
    assert (nav[inside] < 40).all() and (nav[on_wall] > 70).mean() > 0.95
    # the origin is the lower-left corner of cell (0, 0): the room's corner lands where expected
    ix, iy = grid.cell_of(np.array([[x0 + 0.01, y0 + 0.01]]))[0]
    assert occ[iy, ix] or occ[iy, ix + 1] or occ[iy + 1, ix]


def test_log_odds_are_clamped() -> None:
    params = GridParams(resolution_m=0.1)
    kf = room_keyframes(POSES[:1])
    grid = render_grid(params, kf * 50, np.repeat(POSES[:1], 50, axis=0))
    p = grid.probability()[grid.observed]
    assert p.min() >= params.p_min - 1e-6 and p.max() <= params.p_max + 1e-6


def test_incremental_equals_rendered_and_moves_trigger_a_render() -> None:
    params = GridParams(resolution_m=0.05)
    kfs = room_keyframes()
    mapper = GridMapper(params)
    for n in range(1, len(kfs) + 1):
        grid = mapper.update(kfs[:n], POSES[:n])
    assert mapper.renders == 0
    full = render_grid(params, kfs, POSES)
    inc = mapper.grid
    # same cells in the same place (the incremental grid may have grown differently)
    ox, oy = np.round((full.origin - inc.origin) / params.resolution_m).astype(int)
    h, w = full.shape
    np.testing.assert_allclose(inc.log_odds[oy:oy + h, ox:ox + w], full.log_odds, atol=1e-5)
    moved = POSES.copy()
    moved[1, 0] += 0.2  # an optimisation moved a keyframe: the grid is rendered again
    grid = mapper.update(kfs, moved)
    assert mapper.renders == 1
    assert grid is mapper.grid


def test_grid_grows_and_keeps_content() -> None:
    params = GridParams(resolution_m=0.1, padding_m=0.5)
    grid = OccupancyGrid.covering(params, np.array([0.0, 0.0]), np.array([1.0, 1.0]))
    grid.insert_scan(np.array([0.5, 0.5, 0.0]), np.array([[0.3, 0.0]]))
    before = grid.occupied_mask().sum()
    grid.insert_scan(np.array([0.5, 0.5, 0.0]), np.array([[8.0, 5.0]]))  # far outside
    assert grid.occupied_mask().sum() >= before + 1
    ix, iy = grid.cell_of(np.array([[0.8, 0.5]]))[0]
    assert grid.occupied_mask()[iy, ix]


def test_nav2_export_round_trip(tmp_path: Path) -> None:
    import cv2

    grid = render_grid(GridParams(resolution_m=0.05), room_keyframes(), POSES)
    yaml_path = write_nav2(grid, tmp_path, "map")
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["image"] == "map.png" and meta["mode"] == "trinary"
    assert meta["resolution"] == 0.05
    np.testing.assert_allclose(meta["origin"][:2], grid.origin)
    img = cv2.imread(str(tmp_path / "map.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == grid.shape and img.dtype == np.uint8
    np.testing.assert_array_equal(img, nav2_image(grid))
    # the image is flipped: its last row is the grid's row 0 (lowest y)
    np.testing.assert_array_equal(img[-1] == 254, grid.free_mask()[0])
    assert set(np.unique(img)) <= {0, 205, 254}


def test_point_cloud_gathered_in_chunks_is_the_whole_thinning() -> None:
    """``point_cloud`` thins a few keyframes at a time (a long run's returns are never all in
    memory): the same points, in the same order, as thinning all of them at once."""
    from server.slam.keyframes import voxel_thin
    from server.slam.mapping import hits_in_map

    kfs = room_keyframes()
    assert len(kfs) >= 4
    (whole,) = voxel_thin(hits_in_map(kfs, POSES), 0.05)
    for chunk in (1, 2, 3):
        np.testing.assert_array_equal(point_cloud(kfs, POSES, 0.05, chunk=chunk), whole)


def test_ply_round_trip(tmp_path: Path) -> None:
    kfs = room_keyframes()
    cloud = point_cloud(kfs, POSES, voxel_m=0.05)
    assert len(cloud) > 100
    write_ply(tmp_path / "cloud.ply", cloud)
    back = read_ply_xy(tmp_path / "cloud.ply")
    np.testing.assert_allclose(back, cloud, atol=1e-5)
    x0, y0, x1, y1 = ROOM  # every point lies on a wall
    d = np.minimum.reduce([np.abs(back[:, 0] - x0), np.abs(back[:, 0] - x1),
                           np.abs(back[:, 1] - y0), np.abs(back[:, 1] - y1)])
    assert d.max() < 0.01


def test_returns_past_the_useful_range_do_not_stretch_the_map() -> None:
    """An 80 m laser's far returns clear their beams to max_ray_m and mark nothing."""
    params = GridParams(resolution_m=0.05, max_ray_m=10.0, padding_m=1.0)
    grid = OccupancyGrid(params)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    hits = np.c_[np.cos(angles), np.sin(angles)] * 80.0
    hits[:10] *= 0.05                              # ten walls at 4 m
    for _ in range(3):
        grid.insert_scan(np.zeros(3), hits)
    h, w = grid.shape
    assert max(h, w) * params.resolution_m <= 2 * (10.0 + 1.0) + 0.2
    assert grid.occupied_mask().sum() >= 10         # the near walls are mapped
    ix, iy = grid.cell_of(np.array([[9.5, 0.01]]))[0]
    assert grid.free_mask()[iy, ix]                 # free up to max_ray_m


def test_memory_follows_the_area_seen_not_its_bounding_box() -> None:
    """A diagonal corridor 120 m long: the tiles hold about the strip the beams crossed."""
    params = GridParams(resolution_m=0.05, max_ray_m=4.0)
    grid = OccupancyGrid(params)
    angles = np.linspace(-math.pi, math.pi, 180, endpoint=False)
    ring = np.c_[np.cos(angles), np.sin(angles)] * 3.0
    for d in np.arange(0.0, 120.0, 1.0):
        grid.insert_scan(np.array([d * 0.7071, d * 0.7071, 0.0]), ring)
    h, w = grid.shape
    dense = h * w * 2                                   # int16 over the bounding box
    assert grid.nbytes < 0.25 * dense, (grid.nbytes, dense)
    strip_cells = 120.0 * 6.0 / params.resolution_m ** 2
    assert grid.tiles * 64 * 64 < 4 * strip_cells      # tiles: at most 4 × the strip's cells
    assert grid.observed.sum() > 0.9 * strip_cells


def test_dense_copies_are_read_only_and_from_dense_round_trips() -> None:
    rng = np.random.default_rng(1)
    lo = rng.uniform(-1.9, 3.4, (70, 130))
    obs = rng.random((70, 130)) < 0.6
    grid = OccupancyGrid.from_dense(GridParams(), (0.25, -3.0), lo, obs)
    np.testing.assert_array_equal(grid.observed, obs)
    np.testing.assert_allclose(grid.log_odds[obs], lo[obs], atol=6e-4)   # thousandths
    assert (grid.log_odds[~obs] == 0).all()
    try:
        grid.log_odds[0, 0] = 1.0
    except ValueError:
        pass
    else:
        raise AssertionError("a dense copy must not look writable")


def test_a_pickled_grid_keeps_its_cells_and_not_its_spare_capacity() -> None:
    import pickle

    grid = render_grid(GridParams(resolution_m=0.05), room_keyframes(), POSES)
    back = pickle.loads(pickle.dumps(grid))
    np.testing.assert_array_equal(back.quantised(), grid.quantised())
    assert len(back._pool) == back.tiles
    back.insert_scan(POSES[0], room_keyframes()[0].hits)   # and it grows again
    assert back.tiles >= grid.tiles
