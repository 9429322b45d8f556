"""Two halves of one simulated run in the large world, merged offline.

A run of two robots that start facing each other (each sees the other's tag) is simulated in
process with the server core exploring but never merging, and recorded into one MCAP file (the
wire bytes, as the recorder writes them). The recording is split per robot: session A holds r1's
messages, session B r2's, including r2's detections of r1's tag. ``mrslam merge`` must find the
rendezvous in the recorded detections and align B's map frame (r2's first pose) to A's (r1's
first pose) within 5 cm and 1° of the truth, better than the direct method on the first
sighting; a perturbed hand-measured marker must converge as well.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import msgspec
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from mrslam.cli import app
from recording.reader import RecordingError, read_recording
from recording.writer import McapRecorder
from robot_agent.aruco import TagDetector
from schemas import Scan, TagDetection, TagDetections, keys
from schemas.codec import encode
from schemas.messages import quantise_ranges_mm
from schemas.se2 import between, pose_distance
from schemas.tags import CameraMount, TagLayout
from server.config import ServerConfig
from server.core import ServerCore
from server.offline.offline_merge import MergeError, load_session, rename_clashes, run_merge
from sim.loader import load_world
from sim.simulator import SimParams, Simulator
from tests.conftest import DATA

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

WORLD = DATA / "worlds" / "thesis" / "house_large.world"
SPAWN = {"r1": (-5.0, 20.0, 0.0), "r2": (-2.5, 19.5, math.pi)}
T_TRUE = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))
STEPS = 300


def config(**teams: object) -> ServerConfig:
    # (frontiers are looked across from their middle: the robots' first moves then keep r1 in
    # r2's view long enough for a rendezvous; from the near end, r2 turns away at once)
    return ServerConfig.model_validate({
        "slam": {"grid": {"resolution_m": 1 / 15}},
        "explore": {"total_area_m2": 2500, "coverage_threshold": 0.9,
                    "frontier_view": "middle"},
        "teams": teams,
    })


def simulate(path: Path) -> None:
    """The live run without merging (teams off), recorded into ``path``."""
    sim = Simulator(load_world(WORLD), SPAWN, SimParams(), seed=5)
    core = ServerCore(config(enabled=False))
    detector = TagDetector(TagLayout(), CameraMount())
    lidar, K = sim.p.lidar, sim.p.camera.camera.K
    with McapRecorder(path) as rec:
        for _ in range(STEPS):
            obs = sim.sense()
            for rid in SPAWN:
                scan = Scan(robot_id=rid, seq=obs.step + 1, stamp_ns=obs.stamp_ns,
                            odom_pose=obs.odometry[rid][0],
                            angle_min_rad=lidar.angle_min_rad,
                            angle_increment_rad=lidar.angle_increment_rad,
                            range_min_mm=round(lidar.range_min_m * 1000),
                            range_max_mm=round(lidar.range_max_m * 1000),
                            ranges_mm=quantise_ranges_mm(obs.ranges_m[rid], lidar.range_min_m,
                                                         lidar.range_max_m))
                rec.add(keys.robot_scan(rid), encode(scan))
                cmd = core.on_scan(scan)
                rec.add(keys.robot_cmd_vel(rid), encode(cmd))
                sim.set_command(rid, cmd.v_mps, cmd.omega_rps)
            for rid, frame in obs.frames.items():
                dets = [TagDetection(tag_id=s.tag_id, observed_robot_id=s.robot_id,
                                     range_m=s.range_m, bearing_rad=s.bearing_rad,
                                     yaw_rad=s.yaw_rad, sigma_range_m=s.sigma_range_m,
                                     sigma_bearing_rad=s.sigma_bearing_rad,
                                     sigma_yaw_rad=s.sigma_yaw_rad)
                        for s in detector.detect(frame.image, K, rid).sightings]
                if dets:
                    rec.add(keys.robot_tags(rid), encode(TagDetections(
                        robot_id=rid, seq=obs.step + 1, stamp_ns=obs.stamp_ns,
                        detections=dets)))
            sim.advance()
    assert not core.merges


def split(run: Path, robot_id: str, out: Path, tags: bool = True) -> Path:
    """One robot's messages of a recording, as a session of its own (in chunks of ~1 s, as
    the recorder's periodic flushes leave them)."""
    with McapRecorder(out, chunk_size=16_000) as rec:
        for m in read_recording(run).in_time_order():
            if keys.robot_id_of(m.topic) == robot_id and (tags or not m.topic.endswith("/tags")):
                rec.add(m.topic, m.data)
    return out


@pytest.fixture(scope="module")
def halves(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("run")
    simulate(d / "run.mcap")
    # A's robot left its tag where B's saw it: only B's sightings are kept
    return (split(d / "run.mcap", "r1", d / "a.mcap", tags=False),
            split(d / "run.mcap", "r2", d / "b.mcap"))


def error(T: dict[str, float]) -> tuple[float, float]:
    return pose_distance(between(T_TRUE, np.array([T["x_m"], T["y_m"], T["theta_rad"]])))


def test_halves_merge_from_the_recorded_sighting(halves: tuple[Path, Path],
                                                 tmp_path: Path) -> None:
    a, b = halves
    out = tmp_path / "merged"
    res = CliRunner().invoke(app, ["merge", str(a), str(b), "--out", str(out)])
    assert res.exit_code == 0, res.output
    rep = json.loads((out / "merge_report.json").read_text())
    assert rep["rendezvous"] == "sightings" and rep["sightings_used"] >= 3
    assert rep["sessions"]["a"]["tag_messages"] == 0
    et, er = error(rep["transform"])
    dt, dr = error(rep["direct_first_sighting"])
    print(f"offline merge error {et:.4f} m {math.degrees(er):.3f} deg; "
          f"direct {dt:.4f} m {math.degrees(dr):.3f} deg; map matches {rep['map_matches']}")
    assert et <= 0.05 and er <= math.radians(1.0)
    assert et < dt
    cov = np.array(rep["covariance"])
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert rep["map_agreement"]["conflict_ratio"] <= 0.1
    assert rep["sessions"]["a"]["unreadable_messages"] == 0
    # one merged map, both trajectories in it
    teams = list((out / "maps").iterdir())
    assert len(teams) == 1
    meta = yaml.safe_load((teams[0] / "map.yaml").read_text())
    assert (teams[0] / meta["image"]).stat().st_size > 0
    assert (teams[0] / "points.ply").stat().st_size > 0
    for rid in ("r1", "r2"):
        rows = (out / "trajectories" / f"{rid}_final.csv").read_text().splitlines()
        assert len(rows) > 100


def test_a_perturbed_marker_is_corrected_on_the_maps(halves: tuple[Path, Path],
                                                     tmp_path: Path) -> None:
    a, b = halves
    off = np.array([T_TRUE[0] + 0.3 / math.sqrt(2), T_TRUE[1] - 0.3 / math.sqrt(2),
                    T_TRUE[2] + math.radians(3.0)])
    rep = run_merge(a, b, tmp_path / "m", marker=",".join(f"{v:.6f}" for v in off),
                    cfg=config())
    et, er = error(rep["transform"])
    print(f"marker merge error {et:.4f} m {math.degrees(er):.3f} deg, "
          f"map matches {rep['map_matches']}")
    assert rep["rendezvous"] == "marker" and rep["map_matches"] > 0
    assert et <= 0.05 and er <= math.radians(1.0)


def test_one_robot_in_both_sessions_is_renamed(halves: tuple[Path, Path]) -> None:
    _, b = halves
    A, B = load_session(b), load_session(b)
    rename_clashes(B, set(A.robots))
    assert B.robots == ["r2b"] and {m.robot_id for m in B.scans} == {"r2b"}
    assert {m.robot_id for m in B.tags} == {"r2b"}
    # its sightings of another session's robot keep that robot's id
    assert B.tags and all(d.observed_robot_id == "r1" for m in B.tags for d in m.detections)
    Bs = load_session(b)
    Bs.tags = [msgspec.structs.replace(m, detections=[
        msgspec.structs.replace(d, observed_robot_id="r2") for d in m.detections])
        for m in Bs.tags]
    rename_clashes(Bs, {"r2"})  # its own robot's id is taken: its sightings of it follow
    assert Bs.robots == ["r2b"]
    assert all(d.observed_robot_id == "r2b" for m in Bs.tags for d in m.detections)


def test_a_truncated_session_is_recovered_or_refused(halves: tuple[Path, Path],
                                                     tmp_path: Path) -> None:
    a, b = halves
    data = b.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    rep = run_merge(a, cut, tmp_path / "m", cfg=config())
    s = rep["sessions"]["b"]
    assert not s["intact"] and s["unreadable_messages"] + s["skipped_bytes"] > 0
    et, _ = error(rep["transform"])
    assert et <= 0.1
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(data[:8] + bytes(5000))
    with pytest.raises(RecordingError):
        run_merge(a, junk, tmp_path / "n")
    res = CliRunner().invoke(app, ["merge", str(a), str(junk), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "junk.mcap" in res.output
    res = CliRunner().invoke(app, ["merge", str(a), str(b), "--out", str(tmp_path / "p"),
                                   "--marker", "1,2"])
    assert res.exit_code == 2 and "X,Y,YAW" in res.output
    with pytest.raises(MergeError, match="no robot scan"):
        empty = split(a, "r9", tmp_path / "none.mcap")
        run_merge(a, empty, tmp_path / "q")


def relabel(session: Path, robot_id: str, shift_ns: int, out: Path) -> Path:
    """A session as if another run of robot ``robot_id`` had recorded it ``shift_ns`` later."""
    with McapRecorder(out) as rec:
        for m in read_recording(session).in_time_order():
            if m.topic.endswith("/scan"):
                s = msgspec.msgpack.decode(m.data, type=Scan)
                s = msgspec.structs.replace(s, robot_id=robot_id, stamp_ns=s.stamp_ns + shift_ns)
                rec.add(keys.robot_scan(robot_id), encode(s))
    return out


def test_one_robot_two_runs_at_different_times_merge_by_marker(
        halves: tuple[Path, Path], tmp_path: Path) -> None:
    """The corridor experiment: one robot (r1) in both sessions, an hour apart."""
    a, b = halves
    later = relabel(b, "r1", 3600 * 10**9, tmp_path / "later.mcap")
    with pytest.raises(MergeError, match="--marker"):
        run_merge(a, later, tmp_path / "x", cfg=config())
    off = T_TRUE + np.array([-0.2, 0.2, math.radians(-2.0)])
    rep = run_merge(a, later, tmp_path / "m", marker=",".join(f"{v:.6f}" for v in off),
                    cfg=config())
    assert rep["robot_b"] == "r1b" and rep["sessions"]["b"]["renamed"] == {"r1": "r1b"}
    et, er = error(rep["transform"])
    assert et <= 0.05 and er <= math.radians(1.0)
    assert (tmp_path / "m" / "trajectories" / "r1b_final.csv").exists()
