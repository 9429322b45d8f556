"""The loss watch: when a placed robot's scans disagree with the map long enough to be lost."""

from __future__ import annotations

from server.knownmap.config import KnownMapConfig
from server.knownmap.watch import Agreement, LossWatch

S = 1_000_000_000          # a second [ns]
STEP = S // 10             # a scan every 0.1 s


def _watch() -> LossWatch:
    k = KnownMapConfig()
    return LossWatch(k.lost_conflict_ratio, k.lost_after_s)


def _run(w: LossWatch, a: Agreement, seconds: float, t0: int = 0) -> float | None:
    """Feed ``a`` every scan for ``seconds``: when the robot was lost (s), None if not."""
    for n in range(int(seconds * 10) + 1):
        if w.update(a, t0 + n * STEP, 0):
            return n * STEP / S
    return None


def test_a_robot_carried_where_its_scans_half_agree_is_lost_after_lost_after_s() -> None:
    # the bench's lost seed 4: 213 returns on mapped walls, 173 in open space (0.45)
    lost = _run(_watch(), Agreement(213, 173), 5.0)
    assert lost is not None and lost <= KnownMapConfig().lost_after_s + 0.15


def test_a_placed_robot_among_closed_doors_and_moved_boxes_is_not_lost() -> None:
    # the most a placed robot's scans disagreed for 1.5 s in the changed house: 0.13
    assert _run(_watch(), Agreement(87, 13), 30.0) is None


def test_one_scan_that_agrees_starts_the_count_again() -> None:
    w = _watch()
    after = KnownMapConfig().lost_after_s
    assert _run(w, Agreement(50, 50), after - 0.3) is None
    assert not w.update(Agreement(95, 5), int((after - 0.2) * S), 3)
    assert w.bad_since_ns is None and w.good_keyframes == 3
    lost = _run(w, Agreement(50, 50), 5.0, t0=int((after - 0.1) * S))
    assert lost is not None and lost >= after - 0.05


def test_a_scan_with_little_mapped_ground_in_view_says_nothing() -> None:
    w = _watch()
    assert _run(w, Agreement(5, 20), 10.0) is None     # 25 returns: under MIN_KNOWN_RETURNS
    assert w.bad_since_ns is None
