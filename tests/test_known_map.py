"""Missions on a known map (server/knownmap, server/runtime/mapstore, mapfind): maps on disk
and their versions, robots at unknown poses placed in a map, never placed wrongly in a
building of rooms alike, a robot carried away noticed and placed again, and the two modes.

The maps here are surveyed from the truth (``bench.support.survey``: scans at known poses, in
the world's frame), which costs a second where exploring would cost minutes; the benchmark
(``bench/known_map.py``) uses the map of a finished demo."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench.support.known_mission import (
    WORLDS,
    KnownMission,
    demo_config,
    free_poses,
    mission,
    pose_away,
)
from bench.support.survey import survey_map
from server.command.operator import OperatorCommand
from server.config import ServerConfig
from server.console.model import ConsoleModel
from server.core import ServerCore
from server.knownmap.ghosts import MAP_ID
from server.knownmap.mapdata import KnownMap
from server.runtime.mapfind import find_map, leave_map, start_map
from server.runtime.mapstore import FORMAT_VERSION, MapError, read_map, write_map

HOUSE = WORLDS / "small_house.world"
WINGS = WORLDS / "ambiguous_wings.world"


@pytest.fixture(scope="module")
def house() -> KnownMap:
    return survey_map(HOUSE)


def _part(known: KnownMap, keep: list[int]) -> KnownMap:
    return KnownMap([known.keyframes[k] for k in keep], known.poses[keep],
                    [known.sources[k] for k in keep], known.resolution_m, known.anchor)


def _house_mission(known: KnownMap, spawn: np.ndarray, mode: str = "localize",
                   seed: int = 0, **more: object) -> KnownMission:
    return mission(HOUSE, known, {"r1": spawn}, demo_config("small-house-3", mode=mode, **more),
                   np.zeros(3), seed=seed)


def _one_line(e: pytest.ExceptionInfo[MapError]) -> str:
    text = str(e.value)
    assert "\n" not in text
    return text


# -- on disk ---------------------------------------------------------------------------------
def test_a_map_saved_reads_back_as_it_was(house: KnownMap, tmp_path: Path) -> None:
    part = _part(house, list(range(0, len(house), 7)))
    part.missions, part.notes = 3, {"made": "a test"}
    folder = write_map(part, tmp_path / "known_map", site="small_house", written_by="test")
    back = read_map(folder, site="small_house")
    assert len(back) == len(part) > 5
    np.testing.assert_array_equal(back.poses, part.poses)
    np.testing.assert_array_equal(back.stamps_ns, part.stamps_ns)
    assert back.sources == part.sources and back.missions == 3
    assert back.notes == {"made": "a test"} and back.resolution_m == part.resolution_m
    for a, b in zip(part.keyframes, back.keyframes, strict=True):
        np.testing.assert_array_equal(a.T_odom_robot, b.T_odom_robot)
        np.testing.assert_array_equal(a.matchable.points, b.matchable.points)
        np.testing.assert_array_equal(a.matchable.normals, b.matchable.normals)
        np.testing.assert_array_equal(a.matchable.ranges_m, b.matchable.ranges_m)
        assert a.matchable.fov_rad == b.matchable.fov_rad
        for x, y in zip(a.render.points(), b.render.points(), strict=True):
            np.testing.assert_allclose(x, y, atol=1e-6)      # float32 on disk, as in memory
    # found by what a user names: the folder itself, or the run folder holding it
    assert len(find_map(folder)[0]) == len(part)
    (tmp_path / "run" / "server").mkdir(parents=True)
    write_map(part, tmp_path / "run" / "server" / "known_map")
    known, where = find_map(tmp_path / "run")
    assert len(known) == len(part) and "server/known_map" in where


def test_a_map_of_a_newer_format_or_another_site_is_refused_in_one_line(
        house: KnownMap, tmp_path: Path) -> None:
    folder = write_map(_part(house, [0, 1, 2]), tmp_path / "known_map", site="small_house")
    head = json.loads((folder / "map.json").read_text())
    (folder / "map.json").write_text(json.dumps({**head, "version": FORMAT_VERSION + 1}))
    with pytest.raises(MapError) as e:
        read_map(folder)
    assert f"format version {FORMAT_VERSION + 1}" in _one_line(e)
    assert f"reads version {FORMAT_VERSION}" in str(e.value)
    (folder / "map.json").write_text(json.dumps({**head, "format": "something-else"}))
    with pytest.raises(MapError) as e:
        find_map(tmp_path)
    assert "not an mrslam map" in _one_line(e)
    (folder / "map.json").write_text(json.dumps(head))
    with pytest.raises(MapError) as e:
        read_map(folder, site="ambiguous_wings")
    assert "'small_house'" in _one_line(e) and "'ambiguous_wings'" in str(e.value)
    (folder / "keyframes.npz").write_bytes(b"not a zip")
    with pytest.raises(MapError) as e:
        read_map(folder)
    assert "damaged" in _one_line(e)


def test_a_path_without_a_map_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(MapError) as e:
        find_map(tmp_path / "nowhere")
    assert "no such folder" in _one_line(e)
    (tmp_path / "file").write_text("x")
    with pytest.raises(MapError) as e:
        find_map(tmp_path / "file")
    assert "not a folder" in _one_line(e)
    with pytest.raises(MapError) as e:
        find_map(tmp_path)
    assert "holds no map" in _one_line(e)


def test_a_run_keeps_the_map_it_started_on_and_leaves_its_own(house: KnownMap,
                                                              tmp_path: Path) -> None:
    part = _part(house, list(range(0, len(house), 5)))
    write_map(part, tmp_path / "old" / "known_map", site="small_house")
    cfg = ServerConfig.model_validate({"known_map": {"path": str(tmp_path / "old"),
                                                     "site": "small_house"}})
    state = tmp_path / "state"
    state.mkdir()
    known = start_map(cfg, state)
    assert known is not None and len(known) == len(part)
    assert len(read_map(state / "known_map")) == len(part)      # the run's own copy
    # resumed: the copy, whatever the path says now
    gone = cfg.model_copy(update={"known_map": cfg.known_map.model_copy(
        update={"path": str(tmp_path / "nowhere")})})
    again = start_map(gone, state)
    assert again is not None and len(again) == len(part)
    # a run that started without a map stays without one
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "journal-000001.mcap").write_bytes(b"")
    assert start_map(cfg, tmp_path / "plain") is None
    # the map a mission leaves: the same keyframes, one mission more
    leave_map(ServerCore(cfg, known=known), tmp_path / "out", cfg)
    left = read_map(tmp_path / "out" / "known_map", site="small_house")
    assert len(left) == len(part) and left.missions == 2
    np.testing.assert_allclose(left.poses, part.poses, atol=1e-6)


def test_a_placement_won_again_confirms_its_guess() -> None:
    """Queries a second apart, the robot moved and turned: the same place wins twice."""
    from server.knownmap.placing import Placement
    from server.knownmap.search import Search

    s = Search(("r1",))
    rng = np.random.default_rng(0)
    for k in range(200):
        T = np.array([1.35, -2.0, -1.457]) + rng.normal(0, [0.03, 0.03, 0.005])
        pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-3, 3)])
        g = s.take([Placement(T, (), 140.0, 0.99)], Placement(T, (), 140.0, 0.99), pose, k)
        assert g is not None and g.wins == k + 1
    assert len(s.guesses) == 1


# -- missions --------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_robot_at_an_unknown_pose_is_placed_in_the_small_house(house: KnownMap) -> None:
    spawn = free_poses(HOUSE, 1, np.random.default_rng(3))[0]
    m = _house_mission(house, spawn, seed=3)
    first = m.core.robot_states(0)          # no scan yet: no robot
    assert not first.robots
    m.step()
    assert [r.localisation for r in m.core.robot_states(0).robots] == ["searching"]
    m.run_until(20.0, lambda m: bool(m.placed))
    assert m.placed, m.core.known.summary() if m.core.known else None
    p = m.placed[0]
    assert p.error_m <= 0.10 and p.error_deg <= 1.0, p
    assert m.core.known is not None and m.core.known.state_of(m.core.robots["r1"]) == "placed"
    # what the operator's page shows
    page = ConsoleModel()
    page.on_robots(m.core.robot_states(int(m.sim_time_s * 1e9)), 0.0)
    assert page.robots["r1"]["localisation"] == "placed"


@pytest.mark.slow
def test_a_robot_in_mirror_image_wings_is_never_placed_wrongly() -> None:
    known = survey_map(WINGS)
    spawn = free_poses(WINGS, 1, np.random.default_rng(0))[0]
    m = mission(WINGS, known, {"r1": spawn}, demo_config("ambiguous-2"), np.zeros(3))
    m.run_until(30.0)
    assert m.core.known is not None and m.core.known.counts["queries"] >= 20
    assert not m.wrong(), m.wrong()
    for p in m.placed:       # placed only once what it saw told the wings apart
        assert p.error_m <= 0.10 and p.error_deg <= 1.0, p


@pytest.mark.slow
def test_a_robot_carried_away_is_noticed_lost_and_placed_again(house: KnownMap) -> None:
    rng = np.random.default_rng(1)
    m = _house_mission(house, free_poses(HOUSE, 1, rng)[0], seed=1)
    m.run_until(15.0, lambda m: bool(m.placed))
    assert m.placed
    before = m.core.fleet.robots[MAP_ID].slam.keyframe_poses().copy()
    at = np.array(m.sim.robots["r1"].pose)
    m.sim.teleport("r1", tuple(pose_away(HOUSE, at, 5.0, rng)))
    t = m.sim_time_s
    m.run_until(t + 30.0, lambda m: len(m.placed) >= 2)
    assert m.core.known is not None
    assert m.core.known.counts["lost"] == 1
    lost = [e for e in m.core.events.all if e.kind == "robot_lost"]
    assert len(lost) == 1 and lost[0].stamp_ns * 1e-9 - t <= 5.0
    assert len(m.placed) == 2, m.core.known.summary()
    again = m.placed[1]
    assert again.error_m <= 0.10 and again.error_deg <= 1.0, again
    after = m.core.fleet.robots[MAP_ID].slam.keyframe_poses()
    assert np.abs(after - before).max() <= 0.01         # the map did not move
    left = m.core.known.mission_map()
    assert left is not None and len(left) == len(house)  # nothing added while lost


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["localize", "extend"])
def test_localize_keeps_the_map_extend_maps_new_ground(house: KnownMap, mode: str) -> None:
    """The map knows the house's west half; a robot placed there is sent east."""
    west = _part(house, [k for k in range(len(house)) if house.poses[k, 0] < 0])
    # (no pass over the map first: the robot goes where it is sent at once)
    m = _house_mission(west, np.array([-8.0, 9.0, 0.0]), mode, inspect=False)
    m.run_until(15.0, lambda m: bool(m.placed))
    assert m.placed and m.placed[0].error_m <= 0.10
    m.core.operate(OperatorCommand("goto", "r1", (3.0, 9.0)), int(m.sim_time_s * 1e9))
    m.run_until(m.sim_time_s + 25.0)
    assert m.core.known is not None
    left = m.core.known.mission_map()
    assert left is not None
    # the map's keyframes it keeps have not moved (extend retires those seen again)
    kept = [k for k, s in enumerate(left.sources) if s == "survey"]
    at = {int(t): k for k, t in enumerate(west.stamps_ns)}
    np.testing.assert_allclose(left.poses[kept],
                               west.poses[[at[int(left.stamps_ns[k])] for k in kept]],
                               atol=0.01)
    added = [s for s in left.sources if s != "survey"]
    if mode == "localize":
        assert len(left) == len(west) and not added
    else:
        # its keyframes (the map left keeps one of a mission's keyframes within 0.5 m that
        # see the same)
        assert len(added) >= 5 and set(added) == {"2:r1"}
        assert left.missions == 2
