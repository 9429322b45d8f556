"""Merge two recorded sessions offline with the live server's SLAM and merge machinery.

    A, B      = read both recordings (robot scans and tag detections; damage tolerated, counted)
    B         = B's robots renamed where their ids clash with A's (r1 -> r1b)
    core      = ServerCore(cfg, navigate=False)          # per-robot SLAM, rendezvous, teams
    for msg in A ∪ B by stamp: core.on_scan / core.on_tags  # sightings merge as they would live
    marker    : a loose, robust link A's first pose -> B's first pose, then the usual checks
                (map agreement, map matching) and refinement on the overlapping maps
    outputs   = merged map, trajectories (write_outputs) + merge_report.json

Both sessions are replayed on one clock: a sighting is placed on the two robots' poses at the
sighting's stamp, so a detection in B of a robot of A is only usable when A covers that moment
(two halves of one run, or sessions that overlap in time). Sessions recorded at different times
need ``--marker``.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

from recording.reader import ReadReport, read_recording
from schemas import Scan, TagDetections, keys
from schemas.codec import decode
from schemas.errors import SchemaError
from schemas.se2 import compose, inverse, wrap_angle
from schemas.types import ID_PATTERN
from server.config import ServerConfig
from server.core import ServerCore
from server.fleet.model import MergeRecord
from server.rendezvous.evidence import MergeProposal
from server.rendezvous.maps import cross_matches
from server.runtime import heap

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: a marker measured by hand: loose, so the maps' overlap decides the final alignment
MARKER_SIGMA_M, MARKER_SIGMA_RAD = 0.5, math.radians(10.0)


class MergeError(ValueError):
    """The sessions cannot be merged (no robot data, no rendezvous, the maps disagree)."""

    user_error = True


@dataclass
class Session:
    path: Path
    scans: list[Scan] = field(default_factory=list)
    tags: list[TagDetections] = field(default_factory=list)
    robots: list[str] = field(default_factory=list)   # by first scan
    renamed: dict[str, str] = field(default_factory=dict)
    read: ReadReport | None = None
    undecodable: Counter[str] = field(default_factory=Counter)


def parse_marker(text: str) -> F64:
    """``"X,Y,YAW"`` (m, m, rad) -> pose; raises MergeError naming the problem."""
    parts = text.split(",")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise MergeError(f"marker {text!r}: expected X,Y,YAW as numbers") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise MergeError(f"marker {text!r}: expected three finite numbers X,Y,YAW")
    return np.array([vals[0], vals[1], wrap_angle(vals[2])])


def load_session(path: str | Path) -> Session:
    """The robot scans and tag detections of a recording, in stamp order."""
    rec = read_recording(path)
    s = Session(rec.path, read=rec.report)
    for m in rec.in_time_order():
        rid = keys.robot_id_of(m.topic)
        if rid is None:
            continue
        cls: type[Any] | None = Scan if m.topic == keys.robot_scan(rid) else \
            TagDetections if m.topic == keys.robot_tags(rid) else None
        if cls is None:
            continue
        try:
            msg = decode(m.data, cls)
        except SchemaError as e:
            s.undecodable[cls.__name__] += 1
            log.warning("%s: %s on %s not decoded: %s", s.path, cls.__name__, m.topic, e)
            continue
        if msg.robot_id != rid:
            s.undecodable[cls.__name__] += 1
            continue
        if cls is Scan:
            s.scans.append(msg)
            if rid not in s.robots:
                s.robots.append(rid)
        else:
            s.tags.append(msg)
    if not s.scans:
        raise MergeError(f"{s.path}: no robot scan in the recording")
    return s


def rename_clashes(b: Session, taken: set[str]) -> None:
    """Give B's robots whose ids A uses new ids (r1 -> r1b), in its scans and in its own
    detections of them; detections of other robots keep their ids (A's robots)."""
    for rid in b.robots:
        if rid not in taken:
            continue
        for suffix in ("b", *(f"b{i}" for i in range(2, 100))):
            new = f"{rid[:32 - len(suffix)]}{suffix}"
            if new not in taken and new not in b.robots and re.match(ID_PATTERN, new):
                b.renamed[rid] = new
                taken.add(new)
                break
    if not b.renamed:
        return
    ren = b.renamed
    b.robots = [ren.get(r, r) for r in b.robots]
    b.scans = [msgspec.structs.replace(m, robot_id=ren.get(m.robot_id, m.robot_id))
               for m in b.scans]
    b.tags = [msgspec.structs.replace(
        m, robot_id=ren.get(m.robot_id, m.robot_id),
        detections=[msgspec.structs.replace(d, observed_robot_id=ren[d.observed_robot_id])
                    if d.observed_robot_id in ren else d for d in m.detections])
        for m in b.tags]


def transform_ab(core: ServerCore, a: str, b: str) -> F64:
    """B's own map frame in A's own map frame, from the current (joint) estimate."""
    return compose(inverse(core.robots[a].own_frame_in_team()),
                   core.robots[b].own_frame_in_team())


def transform_covariance(core: ServerCore, a: str, b: str) -> F64:
    """Marginal covariance (x, y, θ) of B's first keyframe in the team frame, rotated from
    its body frame; A's first keyframe is held by the graph's prior."""
    sl = core.robots[b].slam
    cov = np.asarray(sl.graph.isam.marginalCovariance(sl.trajectory.key(0)), dtype=np.float64)
    th = float(sl.keyframe_pose(0)[2])
    c, s = math.cos(th), math.sin(th)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R @ cov @ R.T


def prealign(core: ServerCore, side_a: list[str], side_b: list[str], T_ab: F64,
             rounds: int = 4) -> F64:
    """``T_ab`` (B's team frame -> A's) moved onto the maps' overlap: B's keyframes are
    scan-matched against A's map as ``T_ab`` places them (``cross_matches``), each match
    gives a transform, their weighted mean is the next estimate."""
    T = np.asarray(T_ab, dtype=np.float64)
    for _ in range(rounds):
        est, w = [], []
        for ra in side_a:
            for rb in side_b:
                sa, sb = core.robots[ra].slam, core.robots[rb].slam
                pa, pb = sa.keyframe_poses(), sb.keyframe_poses()
                for m in cross_matches(sa, sb, T_ab=T):
                    # kb's pose by the match, in A's frame, against its pose in B's frame
                    est.append(compose(compose(pa[m.ka], m.T_ka_kb), inverse(pb[m.kb])))
                    w.append(m.inlier_fraction)
        if not est:
            break
        E, W = np.array(est), np.array(w) / sum(w)
        th = math.atan2(float(W @ np.sin(E[:, 2])), float(W @ np.cos(E[:, 2])))
        new = np.array([float(W @ E[:, 0]), float(W @ E[:, 1]), th])
        step = compose(inverse(T), new)
        T = new
        log.info("marker aligned on %d map matches: moved %.3f m %.2f°", len(est),
                 math.hypot(step[0], step[1]), math.degrees(step[2]))
        if math.hypot(step[0], step[1]) < 0.005 and abs(step[2]) < math.radians(0.1):
            break
    return T


def merge_by_marker(core: ServerCore, a: str, b: str, T_ab: F64, stamp_ns: int) -> None:
    """Join A's and B's teams by a marker pose (B's map frame in A's), a loose robust link
    between their first keyframes; the core verifies it on the maps and refines it there."""
    ra, rb = core.robots[a], core.robots[b]
    if ra.team_id == rb.team_id:
        return
    ta, tb = core.teams[ra.team_id], core.teams[rb.team_id]
    sig = np.array([MARKER_SIGMA_M, MARKER_SIGMA_M, MARKER_SIGMA_RAD])
    T_team, link = core.surgery.own_frames_link(a, b, T_ab, sig, "marker", stamp_ns)
    # a hand-measured marker is off by decimetres and degrees, which the strict map check
    # would take for disagreement far from the marker: align on the maps' overlap first
    T_checked = prealign(core, ta.robot_ids, tb.robot_ids, T_team)
    # the proposal's transform: B's team frame -> A's team frame
    core.merger.try_merge(MergeProposal(ta.team_id, tb.team_id, (), T_checked, np.diag(sig ** 2),
                                 T_team), stamp_ns, (link,), kind="marker")


def run_merge(first: str | Path, second: str | Path, out: str | Path,
              marker: str | None = None, cfg: ServerConfig | None = None) -> dict[str, Any]:
    """Merge session ``second`` (B) into ``first`` (A); writes ``out`` and returns the report."""
    from server.runtime.outputs import write_outputs

    T_marker = parse_marker(marker) if marker is not None else None
    A, B = load_session(first), load_session(second)
    rename_clashes(B, set(A.robots))
    a, b = A.robots[0], B.robots[0]
    core = ServerCore(cfg or ServerConfig(), navigate=False)
    # one clock: both sessions interleaved by stamp, a stamp's scans before its sightings
    stream: list[tuple[int, int, Scan | TagDetections]] = [
        (m.stamp_ns, 0, m) for m in A.scans + B.scans]
    ignored_tags = 0
    if T_marker is None:
        stream += [(m.stamp_ns, 1, m) for m in A.tags + B.tags]
    else:  # the hand-measured marker is the rendezvous
        ignored_tags = sum(len(m.detections) for m in A.tags + B.tags)
    stream.sort(key=lambda e: (e[0], e[1]))
    for _, kind, msg in stream:
        if kind == 0:
            core.on_scan(msg)  # type: ignore[arg-type]
            heap.maybe_trim()   # a long session: freed memory back to the system now and then
        else:
            core.on_tags(msg)  # type: ignore[arg-type]
    last_ns = stream[-1][0]
    if T_marker is not None:
        merge_by_marker(core, a, b, T_marker, last_ns)
    merge = next((m for m in core.merges if m.undone_stamp_ns is None
                  and {a, b} <= set(m.robots_a + m.robots_b)), None)
    if core.robots[a].team_id != core.robots[b].team_id or merge is None:
        rejected = [e.message for e in core.event_log if e.kind == "merge_rejected"]
        why = rejected[-1] if rejected else (
            f"no rendezvous: {core.tag_counters['used']} usable sightings between the sessions"
            " (sessions on different clocks need --marker)")
        raise MergeError(f"sessions not merged: {why}")
    report = _report(core, A, B, a, b, merge, T_marker, ignored_tags)
    out_dir = Path(out)
    write_outputs(core, out_dir, {"offline_merge": report})
    (out_dir / "merge_report.json").write_text(json.dumps(report, indent=2))
    return report


def _pose_dict(T: F64) -> dict[str, float]:
    return {"x_m": round(float(T[0]), 5), "y_m": round(float(T[1]), 5),
            "theta_rad": round(float(T[2]), 6)}


def _report(core: ServerCore, A: Session, B: Session, a: str, b: str, merge: MergeRecord,
            T_marker: F64 | None, ignored_tags: int) -> dict[str, Any]:
    T = transform_ab(core, a, b)
    cov = transform_covariance(core, a, b)
    # the merge record relates team frames; in the sessions' own frames for the report
    swap = b in merge.robots_a
    direct = merge.T_direct_first if not swap else inverse(merge.T_direct_first)
    sessions = {}
    for name, s in (("a", A), ("b", B)):
        assert s.read is not None
        sessions[name] = {"path": str(s.path), "robots": s.robots, "renamed": s.renamed,
                          "scans": len(s.scans), "tag_messages": len(s.tags),
                          "messages_read": s.read.messages,
                          "unreadable_messages": s.read.unreadable_messages,
                          "damaged_chunks": s.read.damaged_chunks,
                          "skipped_bytes": s.read.skipped_bytes,
                          "undecodable": dict(s.undecodable),
                          "intact": s.read.intact, "problems": s.read.problems[:10]}
    return {
        "robot_a": a, "robot_b": b,
        "transform": _pose_dict(T),  # B's map frame (its first pose) in A's map frame
        "covariance": cov.round(10).tolist(),
        "sigma": {"x_m": math.sqrt(cov[0, 0]), "y_m": math.sqrt(cov[1, 1]),
                  "theta_rad": math.sqrt(cov[2, 2])},
        "rendezvous": "marker" if T_marker is not None else "sightings",
        "marker": _pose_dict(T_marker) if T_marker is not None else None,
        "direct_first_sighting": _pose_dict(direct) if merge.sightings else None,
        "transform_at_merge": _pose_dict(merge.T_joint if not swap else inverse(merge.T_joint)),
        "map_agreement": merge.agreement,
        "sightings_used": len(merge.sightings),
        "sightings_total": core.tag_counters["used"],
        "map_matches": core.tag_counters["map_matches"],
        "ignored_tag_detections": ignored_tags,
        "tag_counters": dict(core.tag_counters),
        "sessions": sessions,
    }
