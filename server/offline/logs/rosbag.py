"""Reader for ROS bags (ROS 1 ``.bag`` files, ROS 2 bag folders in SQLite or MCAP storage): the
laser scans of one scan topic with the odometry pose of the laser at each.

1. **Scans**: a ``sensor_msgs/LaserScan`` or ``sensor_msgs/MultiEchoLaserScan`` topic (the
   one asked for, else the one with the most messages); of a multi-echo beam, the first echo
   or the last (``echo``). Stamps are the header stamps (the bag's receive time where a header
   stamp is unset).
2. **Odometry**, the first of: a ``nav_msgs/Odometry`` topic (the one asked for, else the one
   with the most messages); ``/tf``: the transforms whose child is the frame the scans hang from
   (through ``/tf_static``); none — then ``RobotSlam`` gets scan-matched odometry
   (``server.offline.logs.scan_odometry``), as it does when asked to ignore the bag's odometry.
3. **Corrupt samples** of that odometry are skipped and counted (``server.offline.logs.odomcheck``);
   if every sample is corrupt, the bag is refused.
4. **Laser pose** on the robot: ``laser_pose`` if given, else the ``/tf_static`` transforms from
   the scans' frame up to the odometry's frame, else the robot's origin (with a warning).
5. Each scan gets the odometry interpolated at its stamp, composed with the laser pose.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schemas.se2 import compose
from server.offline.logs.bagmsgs import (
    ODOMETRY,
    SCAN_TYPES,
    TF_TYPES,
    Echo,
    frame,
    laser_record,
    pose_of,
    stamp,
    transform_of,
    yaw_of,
)
from server.offline.logs.bagsource import BagMessages, is_bag, read_messages
from server.offline.logs.odomcheck import OdometryCheck, OdometryLimits, check_odometry
from server.offline.logs.odometry import interpolate_pose
from server.offline.logs.records import (
    F64,
    BagError,
    CarmenLog,
    LaserRecord,
    OdometryRecord,
    ReadStats,
)

log = logging.getLogger(__name__)

__all__ = ["BagError", "BagInfo", "compose", "is_bag", "read_bag", "yaw_of"]
TF_TOPICS = ("/tf", "/tf_static")
Sample = tuple[float, str, str, F64]     # stamp [s], stamp text, parent frame, pose


@dataclass
class BagInfo:
    """Where a bag's scans and odometry came from, and what was skipped on the way."""

    scan_topic: str
    scan_type: str
    reader: str
    odometry: str = "none: scan matching"
    laser_pose: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    laser_pose_from: str = "none: the robot's origin"
    odometry_samples: int = 0
    odometry_skipped: dict[str, int] = field(default_factory=dict)
    lost: list[str] = field(default_factory=list)

    @property
    def source(self) -> str:
        return f"{self.scan_topic}; odometry {self.odometry}"


@dataclass
class _Collected:
    scans: list[LaserRecord] = field(default_factory=list)
    scan_frame: str = ""
    odometry: list[Sample] = field(default_factory=list)
    odom_child: str | None = None
    #: child frame -> (parent frame, pose of the child in the parent)
    static: dict[str, tuple[str, F64]] = field(default_factory=dict)
    dynamic: dict[str, list[Sample]] = field(default_factory=dict)
    fixed: set[str] = field(default_factory=set)   # children of /tf links that never change


def _choose(topics: dict[str, tuple[str, int]], types: tuple[str, ...], wanted: str | None,
            what: str) -> str | None:
    if wanted is not None:
        if wanted not in topics:
            raise BagError(f"no topic {wanted!r} in the bag (topics: {sorted(topics)})")
        if topics[wanted][0] not in types:
            raise BagError(f"topic {wanted!r} carries {topics[wanted][0]}, not "
                           f"{' or '.join(types)}")
        return wanted
    found = {t: n for t, (ty, n) in topics.items() if ty in types}
    if not found:
        return None
    # a scanner mounted on its side (Cartographer's backpack has one) is no use in 2D
    level = {t: n for t, n in found.items() if "vertical" not in t.lower()} or found
    best = max(level, key=lambda t: level[t])
    if len(found) > 1:
        log.warning("several %s topics %s: using %s (the most messages%s)", what,
                    sorted(found), best, ", not a vertical one" * (level != found))
    return best


def _constant_links(got: _Collected) -> None:
    """Transforms on /tf that never change are mounts: before /tf_static (ROS Hydro, 2013)
    fixed joints were sent on /tf again and again."""
    for child, samples in list(got.dynamic.items()):
        poses = np.array([s[3] for s in samples])
        parents = {s[2] for s in samples}
        if child not in got.static and len(parents) == 1 and len(samples) > 1 and \
                np.ptp(poses, axis=0).max() < 1e-9:
            got.static[child] = (samples[0][2], poses[0])
            got.fixed.add(child)
            del got.dynamic[child]


def _covers(samples: list[Sample], scans: list[LaserRecord], margin_s: float = 1.0) -> bool:
    """Whether the odometry's stamps span most of the scans' (a bag whose odometry is stamped
    on another clock, e.g. sim time beside wall time, has nothing to interpolate)."""
    t = np.array([s[0] for s in samples])
    stamps = np.array([r.stamp_s for r in scans])
    inside = (stamps >= t.min() - margin_s) & (stamps <= t.max() + margin_s)
    return bool(inside.mean() >= 0.5)


def _collect(src: BagMessages, scan_topic: str, odom_topic: str | None, echo: Echo,
             stats: ReadStats) -> _Collected:
    got = _Collected()
    pending = src.messages
    pending.reverse()          # taken from the end, so that each raw message is freed once read
    number = 0
    while pending:
        topic, msgtype, t_ns, raw = pending.pop()
        number += 1
        stats.lines += 1
        try:
            msg = src.decode(raw, msgtype)
            if topic == scan_topic:
                rec = laser_record(msg, msgtype, t_ns, number, echo)
                got.scan_frame = got.scan_frame or frame(msg.header.frame_id)
            elif topic == odom_topic:
                text, t = stamp(msg.header, t_ns)
                pose = pose_of(msg.pose.pose)
                got.odom_child = frame(msg.child_frame_id)
                odom_frame = frame(msg.header.frame_id)
            else:
                trs = [(frame(tr.child_frame_id), frame(tr.header.frame_id),
                        *stamp(tr.header, t_ns), transform_of(tr.transform))
                       for tr in msg.transforms]
        except Exception as e:   # a damaged message: skipped, counted
            stats.skip("corrupt", number, f"{topic}: {type(e).__name__}: {e}")
            continue
        stats.by_kind[topic] += 1
        if topic == scan_topic:
            got.scans.append(rec)
        elif topic == odom_topic:
            got.odometry.append((t, text, odom_frame, pose))
        else:
            for child, parent, text, t, T in trs:
                if topic == "/tf_static":
                    got.static[child] = (parent, T)
                else:
                    got.dynamic.setdefault(child, []).append((t, text, parent, T))
    return got


def _mount(static: dict[str, tuple[str, F64]], start: str, base: str | None
           ) -> tuple[str, F64, list[str]]:
    """Walk the static transforms up from ``start`` (to ``base``, or to the first frame with
    no static parent): that frame, the pose of ``start`` in it, and the frames walked from."""
    pose = np.zeros(3)
    walked: list[str] = []
    at = start
    while at != base and at in static:
        parent, T = static[at]
        pose = compose(T, pose)
        walked.append(at)
        at = parent
        if at in walked:
            raise BagError(f"/tf_static has a loop through {at!r}")
    return at, pose, walked


def _checked(samples: list[Sample], limits: OdometryLimits, what: str, path: Path
             ) -> tuple[list[Sample], OdometryCheck]:
    order = sorted(range(len(samples)), key=lambda i: samples[i][0])
    ordered = [samples[i] for i in order]
    check = check_odometry(np.array([s[0] for s in ordered]),
                           np.array([s[3] for s in ordered]).reshape(-1, 3), limits)
    if not check.keep:
        raise BagError(f"{path}: every odometry sample of {what} is corrupt "
                       f"({dict(check.skipped)}): nothing to place the scans with")
    if check.skipped_total:
        first = ", ".join(f"{ordered[i][1]} ({why})" for i, why in check.examples)
        log.warning("%s: %d of %d odometry samples of %s skipped as corrupt %s, e.g. at %s",
                    path, check.skipped_total, len(samples), what, dict(check.skipped), first)
    return [ordered[i] for i in check.keep], check


def read_bag(path: str | Path, scan_topic: str | None = None, odom_topic: str | None = None,
             echo: Echo = "first", laser_pose: F64 | None = None,
             limits: OdometryLimits | None = None, use_odometry: bool = True
             ) -> tuple[CarmenLog, BagInfo]:
    """The scans of a bag, each with the laser's odometry pose (``laser_pose``; None for every
    scan when the bag has no odometry or ``use_odometry`` is False), the odometry kept, and
    where each came from. Raises ``BagError`` naming what is missing."""
    p = Path(path)
    stats = ReadStats()
    chosen: dict[str, str | None] = {}

    def choose(topics: dict[str, tuple[str, int]]) -> set[str]:
        scan = _choose(topics, SCAN_TYPES, scan_topic, "scan")
        if scan is None:
            raise BagError(f"{p}: no sensor_msgs/LaserScan or MultiEchoLaserScan topic in the "
                           f"bag (topics: { {t: ty for t, (ty, _) in topics.items()} })")
        odom = _choose(topics, (ODOMETRY,), odom_topic, "Odometry") if use_odometry else None
        chosen.update(scan=scan, type=topics[scan][0], odom=odom)
        tf = {t for t in TF_TOPICS if t in topics and topics[t][0] in TF_TYPES}
        return {scan} | ({odom} if odom else set()) | (tf if use_odometry else set())

    bag = read_messages(p, lambda ty: ty in SCAN_TYPES or ty == ODOMETRY or ty in TF_TYPES,
                        choose)
    scan, odom = str(chosen["scan"]), chosen["odom"]
    got = _collect(bag, scan, odom, echo, stats)
    info = BagInfo(scan, str(chosen["type"]), bag.reader, lost=bag.lost)
    if bag.lost:
        stats.truncated_stream = True
        log.warning("%s: parts of the bag could not be read: %s", p, "; ".join(bag.lost[:3]))
    if not got.scans:
        raise BagError(f"{p}: the topic {scan} holds no readable scan")
    _constant_links(got)
    samples: list[Sample] = []
    base = _mount(got.static, got.scan_frame, None)[0]   # the top of the scans' fixed tree
    if got.odometry:
        samples, base = got.odometry, got.odom_child or base
        info.odometry = f"{odom} ({base} in {samples[0][2]})"
    elif use_odometry and odom_topic is not None:
        raise BagError(f"{p}: the topic {odom_topic} holds no readable odometry")
    elif base in got.dynamic:
        samples = got.dynamic[base]
        info.odometry = f"/tf ({base} in {samples[0][2]})"
    if samples and not _covers(samples, got.scans):
        log.warning("%s: the odometry of %s is stamped %.0f–%.0f s, the scans %.0f–%.0f s: "
                    "taking odometry from the scans instead", p, info.odometry,
                    min(s[0] for s in samples), max(s[0] for s in samples),
                    got.scans[0].stamp_s, got.scans[-1].stamp_s)
        samples, info.odometry = [], "none: scan matching (the odometry's stamps miss the scans)"
    T_base_laser = np.zeros(3)
    if samples:
        samples, check = _checked(samples, limits or OdometryLimits(), info.odometry, p)
        info.odometry_samples = len(samples) + check.skipped_total
        info.odometry_skipped = {k: int(v) for k, v in check.skipped.items()}
        top, T, walked = _mount(got.static, got.scan_frame, base)
        T_base_laser = _laser_pose(info, laser_pose, T if top == base else None,
                                   got.scan_frame, base, p)
        if top == base and laser_pose is None and set(walked) & got.fixed:
            info.laser_pose_from = "/tf_static and /tf transforms that never change"
    else:
        info.laser_pose_from = "not needed: scan-matched odometry is the laser's own"
    odometry = [OdometryRecord(text, t, pose, 0) for t, text, _, pose in samples]
    placed = _place(got.scans, odometry, T_base_laser)
    log.info("%s: %d scans on %s (%s), odometry from %s, read by %s", p, len(placed), scan,
             info.scan_type, info.odometry, bag.reader)
    return CarmenLog(placed, odometry, {}, stats), info


def _laser_pose(info: BagInfo, given: F64 | None, from_tf: F64 | None, scan_frame: str,
                base: str, p: Path) -> F64:
    """The laser's pose on the robot: the one given, else /tf_static's, else the origin."""
    if given is not None:
        if from_tf is not None and np.any(from_tf):
            log.warning("%s: the laser pose given (%s) replaces the one of /tf_static (%s)", p,
                        np.round(given, 4).tolist(), np.round(from_tf, 4).tolist())
        info.laser_pose, info.laser_pose_from = [float(v) for v in given], "--laser-pose"
        return np.asarray(given, dtype=np.float64)
    if from_tf is not None:
        info.laser_pose = [float(v) for v in from_tf]
        info.laser_pose_from = ("/tf_static" if scan_frame != base
                                else "the scans' frame is the odometry's")
        return from_tf
    log.warning("%s: no static transform ties the scans' frame %r to the odometry's %r: "
                "taking the laser at the robot's origin (give --laser-pose X,Y,YAW)", p,
                scan_frame, base)
    return np.zeros(3)


def _place(scans: list[LaserRecord], odometry: list[OdometryRecord], T_base_laser: F64
           ) -> list[LaserRecord]:
    if not odometry:
        return scans
    stamps = np.array([o.stamp_s for o in odometry])
    poses = np.array([o.pose for o in odometry])
    placed = []
    for rec in scans:
        robot = interpolate_pose(stamps, poses, rec.stamp_s)
        placed.append(LaserRecord(rec.kind, rec.stamp_text, rec.stamp_s, rec.ranges_m,
                                  rec.angles_rad, rec.max_range_m, compose(robot, T_base_laser),
                                  robot, rec.line_no))
    return placed
