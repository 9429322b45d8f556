"""The CARMEN log reader: every line type, odometry from ODOM or laser lines, bad lines,
compressed and damaged files."""

from __future__ import annotations

import bz2
import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from server.offline.logs import (
    CarmenError,
    LaserLines,
    attach_odometry,
    guess_beam_angles,
    read_log,
    select_stream,
)
from tests.conftest import DATA

R5 = "1.0 2.0 3.0 4.0 5.0"
TAIL = "3.0 4.0 0.2 2.9 4.0 0.2 0.1 0.0 0.5 0.5 0.0"  # laser pose, robot pose, tv rv fsd ssd ta
LOG = f"""# CARMEN Logfile
# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp
PARAM robot_frontlaser_offset 0.10 nohost 0
PARAM robot_rearlaser_offset 0.0 nohost 0
SYNC start 10.0 nohost 0
ODOM 0.0 0.0 0.0 0.1 0.0 0.0 10.000000 host 0.0
FLASER 5 {R5} 1.0 2.0 0.5 0.9 2.0 0.5 10.050000 host 0.05
RLASER 5 {R5} 1.0 2.0 3.64 0.9 2.0 0.5 10.060000 host 0.06
ODOM 1.0 0.0 0.0 0.1 0.0 0.0 11.000000 host 1.0
ROBOTLASER1 0 -1.5 3.0 0.75 30.0 0.01 0 5 {R5} 0 {TAIL} 10.070000 host 0.07
ROBOTLASER1 0 -1.5 3.0 0.75 30.0 0.01 1 5 {R5} 5 9 9 9 9 9 {TAIL} 10.080000 host 0.08
RAWLASER1 0 -1.5 3.0 0.75 30.0 0.01 0 5 {R5} 0 10.500000 host 0.5
LASER1 5 {R5} 10.600000 host 0.6
TRUEPOS 0 0 0 0 0 0 10.7 host 0.7
FLASER 5 1.0 2.0 3.0 10.9 host
FLASER 5 {R5} 1.0 abc 0.5 0.9 2.0 0.5 10.950000 host 0.95
FLASER -3 {R5} 1.0 2.0 0.5 0.9 2.0 0.5 10.960000 host 0.96
FLASER 5 {R5} 1.0 2.0 nan 0.9 2.0 0.5 10.970000 host 0.97
ODOM 1.0 0.0 11.5 host 11.5
ODOM 1.0 0.0 0.0 0.1 0.0 0.0 inf host 0.0
BOGUS 1 2 3 4 12.0 host 12.0
\xe9\xe9 garbage line
FLASER 5 {R5} 1.0 2.0 0.5 0.9 2.0 0.5 12.100000 host 2.1
"""


def write(path: Path, text: str) -> Path:
    data = text.encode("latin-1")
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(data))
    elif path.suffix == ".bz2":
        path.write_bytes(bz2.compress(data))
    else:
        path.write_bytes(data)
    return path


@pytest.mark.parametrize("name", ["log.clf", "log.log.gz", "log.clf.bz2"])
def test_every_line_type_and_bad_lines(tmp_path: Path, name: str) -> None:
    log = read_log(write(tmp_path / name, LOG))
    kinds = log.laser_kinds()
    assert kinds == {"FLASER": 2, "RLASER": 1, "ROBOTLASER1": 2, "RAWLASER1": 1, "LASER1": 1}
    assert len(log.odometry) == 2
    assert log.params["robot_frontlaser_offset"] == "0.10"
    # truncated, non-numeric, negative count, NaN pose, short ODOM, inf stamp, garbage
    assert log.stats.skipped["corrupt"] == 7
    assert log.stats.skipped["unknown message"] == 1  # BOGUS (TRUEPOS/SYNC are known)
    assert log.stats.examples and all(e.startswith("line ") for e in log.stats.examples)

    f = log.lasers[0]
    assert f.kind == "FLASER" and f.stamp_text == "10.050000" and f.stamp_s == 10.05
    np.testing.assert_array_equal(f.ranges_m, [1, 2, 3, 4, 5])
    np.testing.assert_allclose(f.laser_pose, [1.0, 2.0, 0.5])
    np.testing.assert_allclose(f.robot_pose, [0.9, 2.0, 0.5])
    rl = next(r for r in log.lasers if r.kind == "ROBOTLASER1")
    np.testing.assert_allclose(rl.angles_rad, -1.5 + 0.75 * np.arange(5))
    assert rl.max_range_m == 30.0
    np.testing.assert_allclose(rl.laser_pose, [3.0, 4.0, 0.2])
    with_remissions = [r for r in log.lasers if r.kind == "ROBOTLASER1"][1]
    np.testing.assert_array_equal(with_remissions.ranges_m, [1, 2, 3, 4, 5])
    raw = next(r for r in log.lasers if r.kind == "RAWLASER1")
    assert raw.laser_pose is None and raw.stamp_text == "10.500000"
    # the scans of one stream share one read-only array of beam angles (a long log's memory)
    assert with_remissions.angles_rad is rl.angles_rad and not rl.angles_rad.flags.writeable


@pytest.mark.parametrize("name", ["log.clf", "log.clf.bz2"])
def test_scans_read_without_ranges_get_them_again_from_the_file(tmp_path: Path,
                                                               name: str) -> None:
    """``read_log(keep_ranges=False)`` reads and checks every line as a full read does but
    keeps no ranges; ``LaserLines`` reads each scan's ranges again, in file order, and
    refuses a line asked out of order or a file changed between the passes."""
    path = write(tmp_path / name, LOG)
    full, light = read_log(path), read_log(path, keep_ranges=False)
    assert [(r.kind, r.stamp_text, r.line_no) for r in light.lasers] == \
        [(r.kind, r.stamp_text, r.line_no) for r in full.lasers]
    assert light.stats.skipped == full.stats.skipped and len(light.odometry) == 2
    assert all(len(r.ranges_m) == 0 for r in light.lasers)
    lines = LaserLines(path)
    for f, r in zip(full.lasers[::2], light.lasers[::2], strict=True):   # some skipped
        np.testing.assert_array_equal(lines.ranges(r), f.ranges_m)
    with pytest.raises(ValueError, match="asked after"):
        lines.ranges(light.lasers[0])
    lines.close()
    changed = write(tmp_path / ("changed-" + name), LOG.replace("10.070000", "10.071000"))
    lines = LaserLines(changed)
    assert len(lines.ranges(light.lasers[0])) == 5
    rl = next(r for r in light.lasers if r.stamp_text == "10.070000")
    with pytest.raises(CarmenError, match=f"line {rl.line_no} no longer holds"):
        lines.ranges(rl)


def test_old_format_beam_geometry() -> None:
    a180 = guess_beam_angles(180)
    assert a180[0] == -math.pi / 2 and np.allclose(np.diff(a180), math.radians(1.0))
    a361 = guess_beam_angles(361)
    assert np.isclose(a361[-1], math.pi / 2) and np.allclose(np.diff(a361), math.radians(0.5))
    a401 = guess_beam_angles(401)
    assert np.allclose(np.diff(a401), math.radians(0.25))
    odd = guess_beam_angles(91)
    assert np.isclose(odd[-1], math.pi / 2)


def test_stream_selection_prefers_richest_front_format(tmp_path: Path) -> None:
    log = read_log(write(tmp_path / "log.clf", LOG))
    assert {r.kind for r in select_stream(log, "front")} == {"ROBOTLASER1"}
    assert {r.kind for r in select_stream(log, "rear")} == {"RLASER"}
    only_flaser = "\n".join(line for line in LOG.splitlines() if "ROBOTLASER" not in line)
    log2 = read_log(write(tmp_path / "log2.clf", only_flaser))
    assert {r.kind for r in select_stream(log2, "front")} == {"FLASER"}


def test_odometry_from_laser_lines_and_from_odom_lines(tmp_path: Path) -> None:
    log = read_log(write(tmp_path / "log.clf", LOG))
    flaser = [r for r in log.lasers if r.kind == "FLASER"]
    from_laser = attach_odometry(flaser, log.odometry, 0.1, source="laser")
    np.testing.assert_allclose(from_laser[0].T_odom_laser, [1.0, 2.0, 0.5])
    # interpolated between ODOM at t=10 (x=0) and t=11 (x=1), laser 0.1 m ahead
    raw = [r for r in log.lasers if r.kind == "RAWLASER1"]
    (s,) = attach_odometry(raw, log.odometry, 0.1)
    np.testing.assert_allclose(s.T_odom_laser, [0.5 + 0.1, 0.0, 0.0], atol=1e-12)
    from_odom = attach_odometry(flaser, log.odometry, 0.1, source="odom")
    np.testing.assert_allclose(from_odom[0].T_odom_laser, [0.05 + 0.1, 0.0, 0.0], atol=1e-12)


def test_stale_laser_poses_are_replaced_by_interpolated_odometry(tmp_path: Path) -> None:
    lines = []
    for k in range(6):
        t = 10.0 + 0.2 * k
        lines.append(f"ODOM {0.1 * k:.3f} 0.0 0.0 0.5 0.0 0.0 {t:.6f} h 0")
        # the laser line 0.1 s later copies the last ODOM pose verbatim
        lines.append(f"FLASER 5 {R5} {0.1 * k:.3f} 0.0 0.0 {0.1 * k:.3f} 0.0 0.0 {t + 0.1:.6f} h 0")
    log = read_log(write(tmp_path / "stale.clf", "\n".join(lines) + "\n"))
    scans = attach_odometry(select_stream(log), log.odometry)
    # interpolated at t + 0.1: half-way to the next ODOM pose
    np.testing.assert_allclose(scans[2].T_odom_laser, [0.25, 0.0, 0.0], atol=1e-9)


def test_missing_unreadable_and_empty_files(tmp_path: Path) -> None:
    with pytest.raises(CarmenError, match="no such file") as e:
        read_log(tmp_path / "missing.clf")
    assert getattr(e.value, "user_error", False)
    with pytest.raises(CarmenError, match="directory"):
        read_log(tmp_path)
    with pytest.raises(CarmenError, match="no laser scans"):
        read_log(write(tmp_path / "odom_only.clf", "ODOM 0 0 0 0 0 0 1.0 h 0\n"))
    with pytest.raises(CarmenError, match="no laser scans"):
        read_log(write(tmp_path / "binary.clf", "\x00\x01\x02 \xff\xfe\n" * 50))


def test_truncated_compressed_stream_keeps_what_was_read(tmp_path: Path) -> None:
    body = "".join(f"FLASER 5 {R5} 0 0 0 0 0 0 {10 + k}.000000 h 0\n" for k in range(20000))
    full = bz2.compress(body.encode(), compresslevel=1)  # 100 kB blocks
    path = tmp_path / "cut.clf.bz2"
    path.write_bytes(full[: len(full) // 2])
    log = read_log(path)
    assert log.stats.truncated_stream
    assert 0 < len(log.lasers) < 20000


def test_real_logs_first_lines(tmp_path: Path) -> None:
    """The three real logs start with header comments and parse without corrupt lines."""
    for name, n_beams in (("aces", 180), ("mit-csail", 361)):
        with bz2.open(DATA / "carmen" / f"{name}.clf.bz2", "rt") as f:
            head = "".join(next(f) for _ in range(60))
        path = tmp_path / f"{name}_head.clf"
        path.write_text(head)
        log = read_log(path)
        assert log.stats.skipped_total == 0
        assert len(log.lasers[0].ranges_m) == n_beams


def test_readings_at_the_sensor_maximum_are_no_returns(tmp_path: Path) -> None:
    from server.offline.slam_log import process
    from server.slam.config import SlamConfig

    # ROBOTLASER1 with maximum_range 4 m: the 4.0 readings are "nothing seen", not walls
    lines = []
    angles = "0 -1.5707963 3.1415926 0.0174533 4.0 0.01 0 181"
    for k in range(5):
        ranges = " ".join("4.0" if i % 3 == 0 else "2.0" for i in range(181))
        lines.append(f"ROBOTLASER1 {angles} {ranges} 0 {0.1 * k} 0 0 {0.1 * k} 0 0 "
                     f"0 0 0 0 0 {10 + k}.0 h 0")
    log = read_log(write(tmp_path / "max.clf", "\n".join(lines) + "\n"))
    slam, stamps, rejected, _ = process(attach_odometry(select_stream(log), log.odometry),
                                        SlamConfig())
    assert len(stamps) == 5 and rejected == 0
    hits = slam.keyframes[0].hits
    assert np.hypot(hits[:, 0], hits[:, 1]).max() < 2.5
