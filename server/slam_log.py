"""``mrslam slam-log``: the robot SLAM of the server run offline on a CARMEN log or a ROS bag
(a ``sensor_msgs/LaserScan`` topic with odometry: ``server.logs.rosbag``).

Writes into the output folder: ``poses.txt`` (``timestamp x y theta`` per laser scan: the
log's ipc timestamp as written, and the laser pose in the map frame after the final
optimisation), ``map.png``/``map.yaml`` (nav2), ``cloud.ply``, ``summary.json`` and the resolved
``config.yaml``.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Literal

import numpy as np

from schemas.config import ConfigModel
from server.heap import HeapTrimmer
from server.logs import (
    CarmenError,
    CarmenLog,
    OdometryScan,
    attach_odometry,
    choose_odometry_source,
    read_log,
    select_stream,
)
from server.logs.stamps import StampPlan, plan_stamps
from server.slam.config import SlamConfig
from server.slam.export import write_nav2, write_ply
from server.slam.robot import RobotSlam, SlamInputError

log = logging.getLogger(__name__)


class SlamLogConfig(ConfigModel):
    laser: Literal["front", "rear"] = "front"
    odometry: Literal["auto", "laser", "odom"] = "auto"
    write_maps: bool = True
    slam: SlamConfig = SlamConfig()


def laser_offset(clog: CarmenLog, laser: str) -> float:
    """Laser position ahead of the robot [m] (PARAM robot_<front|rear>laser_offset)."""
    raw = clog.params.get(f"robot_{laser}laser_offset", "0")
    try:
        return float(raw)
    except ValueError:
        return 0.0


def process(scans: list[OdometryScan], cfg: SlamConfig,
            progress: Callable[[int], None] | None = None
            ) -> tuple[RobotSlam, list[str], int, StampPlan]:
    """Feed the scans to one ``RobotSlam`` in file order, without the stamps that jump out of
    it (``plan_stamps``); returns it, the stamps (text) of the scans it accepted, how many it
    rejected as bad input, and the stamp plan (what it dropped or re-based)."""
    slam = RobotSlam("a", cfg)
    accepted: list[str] = []
    rejected = 0
    plan = plan_stamps([s.record.stamp_s for s in scans])
    _log_stamp_plan(plan, scans)
    heap = HeapTrimmer(every_s=5.0)
    for n, (i, stamp_s) in enumerate(zip(plan.keep, plan.stamps_s, strict=True)):
        s = scans[i]
        rec = s.record
        ranges = rec.ranges_m
        if rec.max_range_m is not None:  # a reading at the sensor's maximum is no return
            ranges = np.where(ranges >= rec.max_range_m, np.inf, ranges)
        try:
            slam.add_scan(round(stamp_s * 1e9), s.T_odom_laser, ranges, rec.angles_rad)
        except SlamInputError as e:
            rejected += 1
            log.warning("line %d: scan skipped: %s", rec.line_no, e)
            continue
        accepted.append(rec.stamp_text)
        heap.maybe()
        if progress is not None and n % 25 == 0:
            progress(i)
    return slam, accepted, rejected, plan


def _log_stamp_plan(plan: StampPlan, scans: list[OdometryScan]) -> None:
    dropped = sorted(plan.dropped_ahead + plan.dropped_behind)
    for j in dropped[:5]:
        log.warning("line %d: scan skipped: its stamp %s is out of line with its neighbours'",
                    scans[j].record.line_no, scans[j].record.stamp_text)
    if len(dropped) > 5:
        log.warning("%d scans skipped in all for stamps out of line", len(dropped))
    for i, shift in plan.steps:
        log.warning("line %d: the log's clock stepped back; later stamps shifted by %+.3f s",
                    scans[i].record.line_no, shift)


def _read(log_file: Path, cfg: SlamLogConfig, scan_topic: str | None,
          odom_topic: str | None) -> tuple[CarmenLog, list[OdometryScan], str, str]:
    """The log's records, its scans with odometry, the laser and the odometry source."""
    from server.logs.rosbag import is_bag, read_bag

    if is_bag(log_file):
        blog, source = read_bag(log_file, scan_topic, odom_topic)
        return blog, [OdometryScan(r, r.laser_pose) for r in blog.lasers
                      if r.laser_pose is not None], "LaserScan", source
    if scan_topic or odom_topic:
        raise CarmenError(f"{log_file}: --scan-topic and --odom-topic are for ROS bags")
    clog = read_log(log_file)
    if clog.stats.skipped_total:
        log.warning("%s: %d unreadable lines skipped (%s), e.g. %s", log_file,
                    clog.stats.skipped_total, dict(clog.stats.skipped), clog.stats.examples[0])
    lasers = select_stream(clog, cfg.laser)
    source = choose_odometry_source(lasers, clog.odometry, cfg.odometry)
    scans = attach_odometry(lasers, clog.odometry, laser_offset(clog, cfg.laser), source)
    return clog, scans, lasers[0].kind, source


def run(log_file: Path, out: Path, config: Path | None = None, scan_topic: str | None = None,
        odom_topic: str | None = None) -> dict[str, object]:
    """Run SLAM on ``log_file`` (a CARMEN log or a ROS bag) and write the results into
    ``out``; returns the summary."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from schemas.config_loading import load_config, write_resolved

    t0 = time.perf_counter()
    cfg = load_config(SlamLogConfig, config)
    clog, scans, laser, source = _read(Path(log_file), cfg, scan_topic, odom_topic)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_resolved(cfg, out)
    t_read = time.perf_counter()
    with Progress(TextColumn("[bold]slam-log"), BarColumn(), TextColumn("{task.completed}/"
                  "{task.total} scans"), TimeElapsedColumn(), transient=True) as bar:
        task = bar.add_task("scans", total=len(scans))
        slam, stamps, rejected, plan = process(scans, cfg.slam,
                                               lambda i: bar.update(task, completed=i))
        bar.update(task, completed=len(scans))
    t_slam = time.perf_counter()
    _, poses = slam.scan_poses()
    with open(out / "poses.txt", "w") as f:
        for text, (x, y, th) in zip(stamps, poses, strict=True):
            f.write(f"{text} {x:.6f} {y:.6f} {th:.6f}\n")
    if cfg.write_maps:
        write_nav2(slam.occupancy_grid(), out, "map")
        write_ply(out / "cloud.ply", slam.point_cloud())
    duration = scans[-1].record.stamp_s - scans[0].record.stamp_s if scans else 0.0
    summary: dict[str, object] = {
        "log": str(log_file),
        "laser": laser,
        "odometry_source": source,
        "scans": len(stamps),
        "scans_rejected": rejected,
        "stamps_dropped_ahead": len(plan.dropped_ahead),
        "stamps_dropped_behind": len(plan.dropped_behind),
        "clock_steps": [{"scan": i, "shift_s": d} for i, d in plan.steps],
        "keyframes": slam.stats.keyframes,
        "loop_closures": slam.stats.loop_closures,
        "loop_closures_removed": slam.stats.loop_closures_removed,
        "matches": slam.stats.matches,
        "loop_search": asdict(slam.loop_stats),
        "lines": clog.stats.lines,
        "lines_skipped": clog.stats.skipped_total,
        "lines_skipped_by_reason": dict(clog.stats.skipped),
        "stream_truncated": clog.stats.truncated_stream,
        "data_duration_s": duration,
        "read_time_s": t_read - t0,
        "slam_time_s": t_slam - t_read,
        "output_time_s": time.perf_counter() - t_slam,
        "wall_time_s": time.perf_counter() - t0,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{log_file.name}: {len(stamps)} scans, {slam.stats.keyframes} keyframes, "
          f"{slam.stats.loop_closures} loop closures, {summary['wall_time_s']:.1f} s "
          f"→ {out}")
    return summary
