"""Rate-limited logging as docs/time-and-admission.md says it: the first five lines of a kind,
then at most one line per period saying how many were left out."""

from __future__ import annotations

import logging

import pytest

from schemas.ratelog import RateLimitedLog


class Clock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def _lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "ratelog-test"]


def test_a_flood_logs_five_lines_then_one_per_period(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    rl = RateLimitedLog(logging.getLogger("ratelog-test"), clock=clock)
    with caplog.at_level(logging.INFO, logger="ratelog-test"):
        logged = [rl.info("unknown-robot", "refused %d", i) for i in range(1000)]
        assert sum(logged) == 5 and all(logged[:5])
        assert _lines(caplog)[-1] == ("refused 4 (further unknown-robot lines at most every "
                                      "10 s)")
        clock.now_s += 9.9
        assert not rl.info("unknown-robot", "refused late")
        clock.now_s += 0.1                    # one period after the fifth line
        assert rl.info("unknown-robot", "refused again")
        assert _lines(caplog)[-1] == ("refused again (and 996 more unknown-robot since the "
                                      "last such line)")
        for _ in range(50):                   # the next period: one line again, no sooner
            clock.now_s += 1.0
            rl.info("unknown-robot", "refused")
    assert len(_lines(caplog)) == 5 + 1 + 5   # 50 s more: one line per 10 s
    assert rl.seen["unknown-robot"] == 1000 + 2 + 50


def test_kinds_have_quotas_of_their_own(caplog: pytest.LogCaptureFixture) -> None:
    rl = RateLimitedLog(logging.getLogger("ratelog-test"), clock=Clock())
    with caplog.at_level(logging.INFO, logger="ratelog-test"):
        for _ in range(20):
            rl.warning("a", "kind a")
            rl.warning("b", "kind b")
    lines = _lines(caplog)
    assert lines.count("kind a") == 4 and lines.count("kind b") == 4   # + the fifth's note
    assert len(lines) == 10
