"""The server's writer thread: jobs of a kind replace one another while they wait, a failing
job is counted and does not stop the thread, and drain waits for what was submitted."""

from __future__ import annotations

import threading

from server.runtime.writer import BackgroundWriter


def test_a_newer_job_of_a_kind_replaces_the_waiting_one_and_errors_are_counted() -> None:
    errors: list[str] = []
    w = BackgroundWriter(lambda kind, e: errors.append(f"{kind}: {e}"))
    gate, done = threading.Event(), []
    def first() -> None:
        gate.wait(10)
        done.append("first")

    w.submit("snapshot", first)
    assert w.busy("snapshot")
    w.submit("outputs", lambda: done.append("outputs-old"))
    w.submit("outputs", lambda: done.append("outputs-new"))   # replaces the waiting one

    def broken() -> None:
        raise OSError("disk full")

    w.submit("broken", broken)
    gate.set()
    assert w.drain(10)
    assert done == ["first", "outputs-new"] and errors == ["broken: disk full"]
    w.submit("outputs", lambda: done.append("after"))   # the thread lives on
    w.close()
    assert done[-1] == "after" and not w.busy("outputs")
