"""``mrslam slam-log``: the robot SLAM of the server run offline on a CARMEN log or a ROS bag
(``server.offline.logs.rosbag``).

Writes into the output folder: ``poses.txt`` (``timestamp x y theta`` per laser scan: the
log's own stamp as written, and the laser pose in the map frame after the final
optimisation), ``map.png``/``map.yaml`` (nav2), ``cloud.ply``, ``summary.json`` and the resolved
``config.yaml``. How a recording is read, step by step: ``docs/real-data.md``.
"""

from __future__ import annotations

import gc
import json
import logging
import time
from array import array
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol, cast

import numpy as np

import server.offline.lean_numba  # noqa: F401  (first: numba readied without SciPy's BLAS)
from server.offline.logs import (
    CarmenError,
    CarmenLog,
    LaserRecord,
    OdometryScan,
    attach_odometry,
    choose_odometry_source,
    read_log,
    select_stream,
)
from server.offline.logs.carmen import LaserLines
from server.offline.logs.kept import KeptText
from server.offline.logs.records import F64
from server.offline.logs.scan_odometry import ScanOdometry
from server.offline.logs.stamps import StampPlan, plan_stamps
from server.offline.packed import PackedScans, StampTexts
from server.offline.progress import ScanCounter
from server.offline.resident import PageReleaser, release_file_pages
from server.offline.slam_log_config import SlamLogConfig
from server.runtime.heap import HeapTrimmer, trim
from server.slam.config import SlamConfig
from server.slam.export import write_nav2, write_ply
from server.slam.grid import GridParams, OccupancyGrid
from server.slam.keyframes import Keyframe
from server.slam.mapping import GridMapper, point_cloud_parts
from server.slam.robot import RobotSlam, SlamInputError

log = logging.getLogger(__name__)

FIELD_BYTES = 3 << 20   # loop closure's likelihood fields kept (the server: 8 MB)

__all__ = ["SlamLogConfig", "laser_offset", "process", "run"]


class LogScan(Protocol):
    """A scan of a log and the laser's odometry pose at it (None: the log has none)."""

    @property
    def record(self) -> LaserRecord: ...
    @property
    def T_odom_laser(self) -> F64 | None: ...


@dataclass(frozen=True, slots=True)
class BareScan:
    """A scan whose recording has no odometry: the scans give it (``ScanOdometry``)."""

    record: LaserRecord
    T_odom_laser: None = None


def laser_offset(clog: CarmenLog, laser: str) -> float:
    """Laser position ahead of the robot [m] (PARAM robot_<front|rear>laser_offset)."""
    raw = clog.params.get(f"robot_{laser}laser_offset", "0")
    try:
        return float(raw)
    except ValueError:
        return 0.0


def process(scans: Sequence[LogScan], cfg: SlamConfig,
            progress: Callable[[int], None] | None = None, *, jitter_fraction: float = 0.5,
            front: ScanOdometry | None = None, release: bool = False,
            ranges_of: Callable[[LaserRecord], F64] | None = None
            ) -> tuple[RobotSlam, Sequence[str], int, StampPlan]:
    """Feed the scans to one ``RobotSlam`` in file order, without the stamps that jump out of
    it (``plan_stamps``); a scan a little early is fed just after the one before it. Scans
    without odometry get it from ``front`` (made here if not given). Returns the SLAM, the
    stamps (text) of the scans it accepted, how many it rejected as bad input, and the stamp
    plan (what it kept early, dropped or re-based).

    ``release``: ``scans`` is a list that is the scans' only holder, and each scan is dropped
    from it (set to None) once fed, so a long log's scans are freed while its map grows: the
    peak is the larger of the two, not their sum.

    ``ranges_of``: where a scan's ranges come from, if not its record (a log read without
    them: ``LaserLines.ranges``, asked in file order)."""
    slam = RobotSlam("a", cfg)
    lean(slam)
    accepted: list[str] = []
    packed = isinstance(scans, PackedScans)
    taken = array("q")        # with packed scans, the indices of those accepted
    rejected = 0
    plan = plan_stamps(scans.stamps_s.tolist() if isinstance(scans, PackedScans)
                       else [s.record.stamp_s for s in scans], jitter_fraction=jitter_fraction)
    _log_stamp_plan(plan, scans, jitter_fraction)
    if front is None and any(s.T_odom_laser is None for s in scans):
        front = ScanOdometry(cfg)
    heap = HeapTrimmer(every_s=5.0)
    pages = PageReleaser(every_s=30.0)
    release_file_pages()      # the libraries' pages run once at import (``resident``)
    for n, (i, stamp_s) in enumerate(zip(plan.keep, plan.stamps_s, strict=True)):
        s = scans[i]
        if release:
            cast("list[LogScan | None]", scans)[i] = None
        rec = s.record
        ranges = rec.ranges_m if ranges_of is None else ranges_of(rec)
        if rec.max_range_m is not None:  # a reading at the sensor's maximum is no return
            ranges = np.where(ranges >= rec.max_range_m, np.inf, ranges)
        try:
            odom = s.T_odom_laser
            if odom is None:
                assert front is not None
                odom = front.add(stamp_s, ranges, rec.angles_rad)
            slam.add_scan(round(stamp_s * 1e9), odom, ranges, rec.angles_rad)
        except SlamInputError as e:
            rejected += 1
            log.warning("line %d: scan skipped: %s", rec.line_no, e)
            continue
        if packed:
            taken.append(i)
        else:
            accepted.append(rec.stamp_text)
        heap.maybe()
        pages.maybe()
        if progress is not None and n % 25 == 0:
            progress(i)
    if packed:
        return slam, StampTexts(cast("PackedScans", scans), taken), rejected, plan
    return slam, accepted, rejected, plan


@dataclass
class Drawing:
    """What the exported map and point cloud are drawn from once the SLAM is done: the
    keyframes without their matching points, their final poses and the grid's settings. The
    rest of the SLAM (the graph, loop closure's submaps and fields, the matching points) can
    then be freed before drawing: on a long log it is tens of megabytes at the run's highest
    point. The same map and cloud as ``RobotSlam.occupancy_grid`` and ``point_cloud``."""

    keyframes: list[Keyframe]
    poses: F64
    grid_params: GridParams

    @classmethod
    def of(cls, slam: RobotSlam) -> Drawing:
        return cls([kf.for_drawing() for kf in slam.keyframes], slam.keyframe_poses(),
                   GridParams(**slam.cfg.grid.model_dump()))

    def grid(self) -> OccupancyGrid:
        return GridMapper(self.grid_params).update(self.keyframes, self.poses)

    def cloud(self, voxel_m: float = 0.05) -> list[F64]:
        """``point_cloud``'s points in the parts they are gathered in (``write_ply`` writes
        them one after the other)."""
        return point_cloud_parts(self.keyframes, self.poses, voxel_m)


def freed() -> None:
    """Collect what was just dropped (``del`` of a SLAM whose ``Drawing`` was taken; its
    objects hold reference cycles) and return the freed heap to the system, and the
    libraries' pages not run since (``resident``)."""
    gc.collect()
    trim()
    release_file_pages()


def lean(slam: RobotSlam) -> None:
    """What keeps a long log's peak low in ``slam-log`` (the server keeps its settings):
    loop closure's submaps in single precision (half their memory; fields and ICP computed
    from them in double precision, results differing from rounding on), its likelihood fields
    within ``FIELD_BYTES`` (a field is made again in about 1.5 ms when needed). The
    keyframes' matching points stay in double precision: in single precision (5.7 MB less on
    a 91-minute log) fr079's rotation error rose from 0.427° to 0.446°. glibc's mmap
    threshold is left to glibc: fixed at 128 KiB it kept 1.5 MB off a 91-minute log's peak
    but took 18 s more system time (12 million page faults against 3 million)."""
    slam.loops.single_submaps = True
    slam.loops.field_bytes = FIELD_BYTES


def _log_stamp_plan(plan: StampPlan, scans: Sequence[LogScan], fraction: float) -> None:
    dropped = sorted(plan.dropped_ahead + plan.dropped_behind)
    for j in dropped[:5]:
        log.warning("line %d: scan skipped: its stamp %s is out of line with its neighbours'",
                    scans[j].record.line_no, scans[j].record.stamp_text)
    if len(dropped) > 5:
        log.warning("%d scans skipped in all for stamps out of line", len(dropped))
    if plan.early:
        j = plan.early[0]
        log.info("%d scans stamped a little before the one above them (less than %.0f %% of "
                 "the %.3f s period, e.g. line %d, %s) are kept in file order",
                 len(plan.early), 100 * fraction, plan.period_s, scans[j].record.line_no,
                 scans[j].record.stamp_text)
    for i, shift in plan.steps:
        log.warning("line %d: the log's clock stepped back; later stamps shifted by %+.3f s",
                    scans[i].record.line_no, shift)


@dataclass
class Read:
    """A recording read: its records, its scans, and where their odometry came from."""

    clog: CarmenLog
    scans: Sequence[LogScan]
    laser: str
    source: str
    bag: dict[str, object] | None = None   # ``BagInfo`` of a bag, for the summary
    lines: LaserLines | None = None        # the scans' ranges, read again (``stream``)


def read_recording(log_file: Path, cfg: SlamLogConfig, scan_topic: str | None = None,
                   odom_topic: str | None = None, stream: bool = False) -> Read:
    """The scans of a CARMEN log or a ROS bag with their odometry (``cfg.odometry``).

    ``stream``: a CARMEN log's scans are read without their ranges, which ``lines`` reads
    again from the file as the scans are fed (in file order), so that a long log is never
    held whole (a bag is read whole)."""
    from server.offline.logs.odomcheck import OdometryLimits
    from server.offline.logs.rosbag import is_bag, read_bag

    use_odometry = cfg.odometry != "scans"
    if is_bag(log_file):
        pose = np.asarray(cfg.laser_pose, dtype=np.float64) if cfg.laser_pose else None
        blog, info = read_bag(log_file, scan_topic, odom_topic, cfg.echo, pose,
                              OdometryLimits(**cfg.odometry_limits.model_dump()), use_odometry)
        bag_scans: list[LogScan] = [OdometryScan(r, r.laser_pose) if r.laser_pose is not None
                                    else BareScan(r) for r in blog.lasers]
        return Read(blog, bag_scans, blog.lasers[0].kind, info.source, asdict(info))
    if scan_topic or odom_topic or cfg.laser_pose:
        raise CarmenError(f"{log_file}: --scan-topic, --odom-topic and --laser-pose are for ROS "
                          f"bags")
    kept = KeptText() if stream else None
    clog = read_log(log_file, keep_ranges=not stream, kept=kept)
    lines = LaserLines(log_file, kept) if stream else None
    if clog.stats.skipped_total:
        log.warning("%s: %d unreadable lines skipped (%s), e.g. %s", log_file,
                    clog.stats.skipped_total, dict(clog.stats.skipped), clog.stats.examples[0])
    lasers = select_stream(clog, cfg.laser)
    if use_odometry and not clog.odometry and all(r.laser_pose is None for r in lasers):
        log.warning("%s: no odometry in the log (no pose in its laser lines, no ODOM lines): "
                    "taking it from scan matching", log_file)
        use_odometry = False
    kind = lasers[0].kind
    if not use_odometry:
        source = "scans"
        scans: list[LogScan] = [BareScan(r) for r in lasers]
    else:
        source = choose_odometry_source(lasers, clog.odometry, cfg.odometry)
        scans = list(attach_odometry(lasers, clog.odometry, laser_offset(clog, cfg.laser),
                                     source))
    if not stream:
        return Read(clog, scans, kind, source, lines=lines)
    packed = PackedScans(scans)    # the records freed at once, on return (``packed``)
    clog.lasers.clear()
    clog.odometry.clear()
    return Read(clog, packed, kind, source, lines=lines)


def _read(log_file: Path, cfg: SlamLogConfig, scan_topic: str | None,
          odom_topic: str | None) -> tuple[CarmenLog, Sequence[LogScan], str, str]:
    """``read_recording`` as a tuple: records, scans, laser and odometry source."""
    r = read_recording(log_file, cfg, scan_topic, odom_topic)
    return r.clog, r.scans, r.laser, r.source


def run(log_file: Path, out: Path, config: Path | None = None, scan_topic: str | None = None,
        odom_topic: str | None = None, **overrides: object) -> dict[str, object]:
    """Run SLAM on ``log_file`` (a CARMEN log or a ROS bag) and write the results into
    ``out``; returns the summary. ``overrides`` replace keys of the config (``echo``,
    ``laser_pose``, ``odometry``...)."""
    from schemas.config_loading import load_config, validate, write_resolved

    t0 = time.perf_counter()
    release_file_pages()        # the imports' pages: reading the log runs none of them
    cfg = load_config(SlamLogConfig, config)
    given = {k: v for k, v in overrides.items() if v is not None}
    if given:
        cfg = validate(SlamLogConfig, {**cfg.model_dump(), **given})
    rec = read_recording(Path(log_file), cfg, scan_topic, odom_topic, stream=True)
    scans = rec.scans
    n_scans = len(scans)
    duration = scans[-1].record.stamp_s - scans[0].record.stamp_s if scans else 0.0
    freed()                     # the records read, now packed (``PackedScans``)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_resolved(cfg, out)
    t_read = time.perf_counter()
    front = ScanOdometry(cfg.slam, cfg.scan_odometry.params()) \
        if any(s.T_odom_laser is None for s in scans) else None
    with ScanCounter(n_scans) as bar:
        slam, stamps, rejected, plan = process(
            scans, cfg.slam, bar.update, jitter_fraction=cfg.stamp_jitter_fraction,
            front=front, release=True,
            ranges_of=rec.lines.ranges if rec.lines is not None else None)
    if rec.lines is not None:
        rec.lines.close()
    t_slam = time.perf_counter()
    _, poses = slam.scan_poses()
    with open(out / "poses.txt", "w") as f:
        for text, (x, y, th) in zip(stamps, poses, strict=True):
            f.write(f"{text} {x:.6f} {y:.6f} {th:.6f}\n")
    del poses
    counts, loop_search = slam.stats, asdict(slam.loop_stats)
    drawing = Drawing.of(slam)
    del slam
    freed()
    if cfg.write_maps:
        write_nav2(drawing.grid(), out, "map")
        write_ply(out / "cloud.ply", drawing.cloud())
    stats = rec.clog.stats
    summary: dict[str, object] = {
        "log": str(log_file),
        "laser": rec.laser,
        "odometry_source": rec.source,
        "scans_in_log": n_scans,
        "scans": len(stamps),
        "scans_posed_percent": round(100.0 * len(stamps) / max(n_scans, 1), 3),
        "scans_rejected": rejected,
        "stamps_early_kept": len(plan.early),
        "stamps_dropped_ahead": len(plan.dropped_ahead),
        "stamps_dropped_behind": len(plan.dropped_behind),
        "clock_steps": [{"scan": i, "shift_s": d} for i, d in plan.steps],
        "keyframes": counts.keyframes,
        "loop_closures": counts.loop_closures,
        "loop_closures_removed": counts.loop_closures_removed,
        "matches": counts.matches,
        "loop_search": loop_search,
        "scan_odometry": asdict(front.stats) if front is not None else None,
        "bag": rec.bag,
        "lines": stats.lines,
        "lines_skipped": stats.skipped_total,
        "lines_skipped_by_reason": dict(stats.skipped),
        "stream_truncated": stats.truncated_stream,
        "data_duration_s": duration,
        "read_time_s": t_read - t0,
        "slam_time_s": t_slam - t_read,
        "output_time_s": time.perf_counter() - t_slam,
        "wall_time_s": time.perf_counter() - t0,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{Path(log_file).name}: {len(stamps)} of {n_scans} scans posed, "
          f"{counts.keyframes} keyframes, {counts.loop_closures} loop closures, "
          f"{summary['wall_time_s']:.1f} s → {out}")
    return summary
