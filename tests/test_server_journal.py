"""The journal: what the server processed, replayed into a fresh core, gives the same state —
also from a journal cut at any byte (up to its last intact chunk)."""

from __future__ import annotations

import math
import os
import random
import shutil
from pathlib import Path

import numpy as np
import pytest

from schemas import Scan, TagDetection, TagDetections
from server.config import ServerConfig
from server.core import ServerCore
from server.runtime.journal import JournalWriter, ReplayReport, read_journal, replay
from server.runtime.snapshot import Snapshots
from tests.test_rendezvous_merger import BEAMS, WALLS, ranges_from

SPAWN = {"r1": (2.5, 3.0), "r2": (7.5, 6.0)}


def config() -> ServerConfig:
    starts = {rid: [c[0] + 1.0, c[1], math.pi / 2] for rid, c in SPAWN.items()}
    return ServerConfig.model_validate({"robots": list(SPAWN),
                                        "teams": {"start_poses": starts}})


def messages(steps: int) -> list[Scan | TagDetections]:
    """Both robots circling (10 Hz), and a sighting of r2 by r1 now and then."""
    from schemas.messages import quantise_ranges_mm

    out: list[Scan | TagDetections] = []
    for k in range(steps):
        for i, (rid, (cx, cy)) in enumerate(SPAWN.items()):
            a = 0.03 * k
            pose = np.array([cx + math.cos(a), cy + math.sin(a), a + math.pi / 2])
            out.append(Scan(robot_id=rid, seq=k + 1, stamp_ns=k * 100_000_000 + i,
                            odom_pose=(float(pose[0]), float(pose[1]), float(pose[2])),
                            angle_min_rad=-math.pi, angle_increment_rad=2 * math.pi / BEAMS,
                            range_min_mm=50, range_max_mm=12000,
                            ranges_mm=quantise_ranges_mm(ranges_from(pose, WALLS), 0.05, 12.0)))
        if k % 10 == 5:
            out.append(TagDetections(robot_id="r1", seq=k, stamp_ns=k * 100_000_000, detections=[
                TagDetection(tag_id=2, observed_robot_id="r2", range_m=5.0, bearing_rad=0.3,
                             yaw_rad=3.0, sigma_range_m=0.05, sigma_bearing_rad=0.01,
                             sigma_yaw_rad=0.2)]))
    return out


def feed(core: ServerCore, msgs: list[Scan | TagDetections], journal: JournalWriter | None
         ) -> None:
    """As the server's worker does: journal first, then the core."""
    for m in msgs:
        if isinstance(m, Scan):
            if journal is not None:
                journal.scan(m, m.stamp_ns)
            core.on_scan(m, m.stamp_ns)
        else:
            if journal is not None:
                journal.tags(m)
            core.on_tags(m)
    if journal is not None:
        journal.alive("r2", False, msgs[-1].stamp_ns)
    core.set_alive("r2", False)


def state(core: ServerCore) -> dict[str, object]:
    return {
        "poses": {rid: r.pose.tolist() for rid, r in core.robots.items()},
        "keyframes": {rid: r.slam.keyframe_poses().tolist() for rid, r in core.robots.items()},
        "alive": {rid: r.alive for rid, r in core.robots.items()},
        "teams": {tid: (t.robot_ids, t.coverage, t.finished) for tid, t in core.teams.items()},
        "merges": [(m.stamp_ns, m.kind, m.T_joint.tolist()) for m in core.merges],
        "counters": core.tag_counters,
        "events": [(e.kind, e.message) for e in core.event_log],
    }


@pytest.fixture(scope="module")
def journalled(tmp_path_factory: pytest.TempPathFactory
               ) -> tuple[Path, list[Scan | TagDetections], dict[str, object]]:
    folder = tmp_path_factory.mktemp("state")
    msgs = messages(120)
    core = ServerCore(config(), navigate=False)
    j = JournalWriter(folder, flush_period_s=0.0)     # a chunk per message: cuts anywhere
    feed(core, msgs, j)
    j.close()
    assert len(core.teams) == 1 and core.merges   # the known start poses merged them
    return folder, msgs, state(core)


def test_a_replayed_journal_gives_the_same_core(
        journalled: tuple[Path, list[Scan | TagDetections], dict[str, object]]) -> None:
    folder, msgs, live = journalled
    core = ServerCore(config(), navigate=False)
    report = replay(core, folder)
    assert report.entries == len(msgs) + 1 and report.unreadable == 0 and not report.problems
    assert state(core) == live
    assert core.pop_events() == []   # published before the crash: not again


def test_a_journal_cut_at_any_byte_replays_what_it_still_holds(
        journalled: tuple[Path, list[Scan | TagDetections], dict[str, object]],
        tmp_path: Path) -> None:
    folder, msgs, _ = journalled
    data = (folder / "journal-0001.mcap").read_bytes()
    rng = random.Random(7)
    for cut in [*sorted(rng.sample(range(len(data)), 4)), len(data) - 3]:
        dst = tmp_path / f"cut{cut}"
        dst.mkdir()
        (dst / "journal-0001.mcap").write_bytes(data[:cut])
        report = ReplayReport()
        n = sum(1 for _ in read_journal(dst, report))
        assert n <= len(msgs) + 1 and report.problems       # the torn tail is reported
        core = ServerCore(config(), navigate=False)
        assert replay(core, dst).entries == n
        # ... and the state is exactly that of the first n messages
        ref = ServerCore(config(), navigate=False)
        kept = msgs[:n]
        for m in kept:
            if isinstance(m, Scan):
                ref.on_scan(m, m.stamp_ns)
            else:
                ref.on_tags(m)
        if n == len(msgs) + 1:
            ref.set_alive("r2", False)
        assert state(core)["poses"] == state(ref)["poses"]
        shutil.rmtree(dst)


def test_segments_continue_one_another(tmp_path: Path) -> None:
    """A restarted server writes a new segment; replay reads them in order."""
    msgs = messages(40)
    core = ServerCore(config(), navigate=False)
    j1 = JournalWriter(tmp_path)
    feed(core, msgs[:30], j1)          # (and never closed: the server was killed)
    j1.flush()
    resumed = ServerCore(config(), navigate=False)
    first = replay(resumed, tmp_path).entries
    j2 = JournalWriter(tmp_path, first_sequence=first)
    assert j2.path.name == "journal-0002.mcap"
    feed(resumed, msgs[30:], j2)
    j2.close()
    again = ServerCore(config(), navigate=False)
    report = replay(again, tmp_path)
    assert report.segments == 2 and report.entries == len(msgs) + 2
    assert state(again) == state(resumed)


def test_a_snapshot_and_the_journal_after_it_resume_the_core(tmp_path: Path) -> None:
    """Resuming from a snapshot replays only what came after it; the pose graphs are rebuilt
    from their factors (ISAM2 itself is not saved), so poses agree to well under a mm."""
    msgs = messages(120)
    live = ServerCore(config(), navigate=False)
    j = JournalWriter(tmp_path)
    snaps = Snapshots(tmp_path)
    for i, m in enumerate(msgs):
        if i == 150:
            snaps.write(live, j.sequence)
        if isinstance(m, Scan):
            j.scan(m, m.stamp_ns)
            live.on_scan(m, m.stamp_ns)
        else:
            j.tags(m)
            live.on_tags(m)
    j.close()
    loaded = snaps.load()
    assert loaded is not None
    core, since = loaded
    assert since == 150 and len(core.robots) == 2
    report = replay(core, tmp_path, from_sequence=since)
    assert report.skipped == 150 and report.entries == len(msgs)
    a, b = state(core), state(live)
    assert a["teams"].keys() == b["teams"].keys() and a["merges"] == b["merges"]
    assert a["counters"] == b["counters"] and a["events"] == b["events"]
    for rid in live.robots:
        assert len(a["keyframes"][rid]) == len(b["keyframes"][rid])
        assert np.allclose(a["keyframes"][rid], b["keyframes"][rid], atol=1e-4)
    # a newest snapshot cut short is passed over for the one before
    snaps.write(live, len(msgs))
    newest = snaps.paths()[0]
    newest.write_bytes(newest.read_bytes()[:-100])
    again = snaps.load()
    assert again is not None and again[1] == 150


def test_a_state_folder_that_cannot_be_one_is_a_typed_error(tmp_path: Path) -> None:
    from server.runtime.journal import JournalError

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(JournalError, match=r"state folder .*file"):
        JournalWriter(blocker / "state")


def test_arrays_that_never_change_are_stored_once(tmp_path: Path) -> None:
    """Keyframe scans and submaps are read-only and go to ``blobs.bin`` once: a snapshot holds
    what changes, and a second snapshot of the same state adds no array."""
    import pickle

    msgs = messages(120)
    live = ServerCore(config(), navigate=False)
    feed(live, msgs, None)
    kf = live.robots["r1"].slam.keyframes[-1]
    with pytest.raises(ValueError, match="read-only"):
        kf.matchable.points[0, 0] = 1.0
    snaps = Snapshots(tmp_path)
    snaps.write(live, 10)
    blobs = (tmp_path / "blobs.bin").stat().st_size
    body = snaps.paths()[0].stat().st_size
    assert blobs > 0 and body + blobs < 0.5 * len(pickle.dumps(live))
    snaps.write(live, 20)
    assert (tmp_path / "blobs.bin").stat().st_size == blobs
    assert snaps.last_bytes < body + 1000      # only the snapshot itself was written
    loaded = Snapshots(tmp_path).load()        # a new server: reads the store's index
    assert loaded is not None and loaded[1] == 20
    back = loaded[0].robots["r1"].slam.keyframes[-1]
    assert np.array_equal(back.matchable.points, kf.matchable.points)
    assert np.array_equal(back.hits, kf.hits) and np.array_equal(back.misses, kf.misses)
    assert np.array_equal(back.matchable.normals, kf.matchable.normals)
    assert not back.matchable.points.flags.writeable


def test_a_torn_blob_store_falls_back_to_the_snapshot_it_still_serves(tmp_path: Path) -> None:
    """A crash mid-append cuts the store's tail; a snapshot whose arrays were lost with it is
    passed over for the one before."""
    msgs = messages(120)
    live = ServerCore(config(), navigate=False)
    snaps = Snapshots(tmp_path)
    feed(live, msgs[:120], None)
    snaps.write(live, 120)
    kept = (tmp_path / "blobs.bin").stat().st_size
    for m in msgs[120:]:
        live.on_scan(m, m.stamp_ns) if isinstance(m, Scan) else live.on_tags(m)
    snaps.write(live, len(msgs))
    store = tmp_path / "blobs.bin"
    assert store.stat().st_size > kept + 100
    store.write_bytes(store.read_bytes()[:kept + 50])     # torn inside the next record
    loaded = Snapshots(tmp_path).load()
    assert loaded is not None and loaded[1] == 120
    assert store.stat().st_size == kept                   # the torn tail was cut


def test_a_snapshot_written_by_other_code_is_passed_over(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The header holds mrslam's version and a digest of the server's code: an upgraded (or
    edited) server does not unpickle objects whose classes changed, it replays the journal."""
    import server.runtime.snapshot as snapshot

    assert "+" in snapshot.VERSION          # version + code digest
    live = ServerCore(config(), navigate=False)
    feed(live, messages(20), None)
    Snapshots(tmp_path).write(live, 7)
    assert Snapshots(tmp_path).load() is not None
    monkeypatch.setattr(snapshot, "VERSION", "0.1.0+another")
    assert Snapshots(tmp_path).load() is None


def test_a_scan_the_server_gets_to_too_late_is_mapped_but_answered_with_a_stop() -> None:
    """A server behind its robots still maps every scan, but does not steer a robot by what it
    saw longer ago than ``control.max_scan_age_s``: the answer is a stop, and it is counted."""
    core = ServerCore(config())
    moving = 0
    scans = [m for m in messages(60) if isinstance(m, Scan) and m.robot_id == "r1"]
    for m in scans[:-1]:
        cmd = core.on_scan(m, m.stamp_ns + 20_000_000)         # answered 20 ms after
        moving += cmd.v_mps != 0.0 or cmd.omega_rps != 0.0
    assert moving > 0 and core.robots["r1"].late_scans == 0
    last = scans[-1]
    keyframes = len(core.robots["r1"].slam.keyframes)
    cmd = core.on_scan(last, last.stamp_ns + 2_000_000_000)    # two seconds behind
    assert cmd.v_mps == 0.0 and cmd.omega_rps == 0.0 and cmd.stamp_ns == last.stamp_ns
    r = core.robots["r1"]
    assert r.late_scans == 1 and r.scans == len(scans)          # mapped as any other
    assert len(r.slam.keyframes) >= keyframes


def test_a_snapshot_is_tied_to_a_digest_of_the_servers_code() -> None:
    """The version a snapshot carries hashes the server's, the factors' and the schemas'
    sources: a digest of nothing would let another version's snapshot load."""
    import hashlib

    from server.runtime import snapshot

    assert snapshot.VERSION.split("+")[1] != hashlib.blake2b(digest_size=8).hexdigest()


def _body(path: Path) -> bytes:
    import zlib

    from server.runtime.snapshot import MAGIC

    return zlib.decompress(path.read_bytes()[len(MAGIC) + 80:])


def test_a_snapshot_taken_by_a_forked_copy_is_the_one_taken_in_process(tmp_path: Path) -> None:
    """A snapshot begun by forking (a copy of the server pickles it while the core goes on) is
    the state at the fork, byte for byte what pickling it in process gives, and resumes the
    same core (real graphs, replayed from the journal after it)."""
    from server.runtime.snapfork import Forked

    msgs = messages(120)
    live = ServerCore(config(), navigate=False)
    j = JournalWriter(tmp_path / "journal")
    (tmp_path / "in-process").mkdir()
    forked, inproc = Snapshots(tmp_path / "journal"), Snapshots(tmp_path / "in-process")
    inproc.use_fork = False
    for i, m in enumerate(msgs):
        if i == 200:
            job = forked.begin(live, j.sequence)
            assert isinstance(job, Forked)
            inproc.write(live, j.sequence)       # the same state, pickled here
        if isinstance(m, Scan):
            j.scan(m, m.stamp_ns)
            live.on_scan(m, m.stamp_ns)          # goes on while the child pickles
        else:
            j.tags(m)
            live.on_tags(m)
        if i == 230:
            assert forked.finish(job).name == "snapshot-000000000200.pkl"
    j.close()
    assert _body(forked.paths()[0]) == _body(inproc.paths()[0])
    assert forked.last_bytes > 0 and forked.last_cpu_s > 0
    # the server's pages are left as they are: gathering them stalled the worker's faults
    assert forked.huge_pages is None
    loaded = Snapshots(tmp_path / "journal").load()       # a new server: the store's index
    assert loaded is not None and loaded[1] == 200
    core, since = loaded
    replay(core, tmp_path / "journal", from_sequence=since)
    a, b = state(core), state(live)
    assert a["merges"] == b["merges"] and a["events"] == b["events"]
    for rid in live.robots:
        assert np.allclose(a["keyframes"][rid], b["keyframes"][rid], atol=1e-4)
    # the parent learns the child's new blobs: another snapshot of the same state adds none
    forked.finish(forked.begin(live, len(msgs)))
    size = (tmp_path / "journal" / "blobs.bin").stat().st_size
    forked.finish(forked.begin(live, len(msgs) + 1))
    assert (tmp_path / "journal" / "blobs.bin").stat().st_size == size
    assert Snapshots(tmp_path / "journal").load() is not None


def test_a_forked_snapshot_that_fails_is_a_typed_error(tmp_path: Path) -> None:
    from server.runtime.snapfork import SnapshotProcessError

    live = ServerCore(config(), navigate=False)
    feed(live, messages(10), None)
    live.not_picklable = lambda: None  # type: ignore[attr-defined]
    snaps = Snapshots(tmp_path)
    with pytest.raises(SnapshotProcessError, match=r"snapshot 7: .*pickle"):
        snaps.finish(snaps.begin(live, 7))
    assert snaps.paths() == []


class _Hangs:
    """Pickling it never ends (as a child stuck on a lock another thread held at the fork)."""

    def __reduce__(self) -> tuple[object, ...]:
        import time
        time.sleep(3600)
        return (_Hangs, ())


def test_a_snapshot_process_that_hangs_is_ended_and_counted_failed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from server.runtime import snapfork

    monkeypatch.setattr(snapfork, "CHILD_TIMEOUT_S", 2.0)
    live = ServerCore(config(), navigate=False)
    live.hang = _Hangs()   # type: ignore[attr-defined]
    (tmp_path / "state").mkdir()
    snaps = Snapshots(tmp_path / "state")
    job = snaps.begin(live, 1)
    assert isinstance(job, snapfork.Forked)
    with pytest.raises(snapfork.SnapshotProcessError, match="did not finish within 2 s"):
        snaps.finish(job)
    with pytest.raises(ProcessLookupError):
        os.kill(job.pid, 0)                   # ended and reaped: no process left behind
    assert snaps.paths() == []                # and nothing put in place
