"""A server that stops while a snapshot is being taken waits for it: the forked child that
takes it is killed when the thread that forked it ends (Linux's parent-death signal follows
the thread), so a worker that ended first lost the snapshot and logged a failure."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from schemas.bus import Bus, free_local_endpoint
from server.config import ServerConfig
from server.runtime.journal import JournalWriter
from server.runtime.node import ServerNode
from server.runtime.snapshot import Snapshots
from tests.waiting import within


def test_a_snapshot_being_taken_when_the_server_stops_is_written(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    prepare = Snapshots.prepare

    def slow(self: Snapshots, core: Any, sequence: int) -> Any:
        time.sleep(1.5)          # in the forked child: the server stops meanwhile
        return prepare(self, core, sequence)

    monkeypatch.setattr(Snapshots, "prepare", slow)
    endpoint = free_local_endpoint()
    cfg = ServerConfig.model_validate({"snapshot_period_s": 0.2,
                                       "bus": {"connect": [endpoint]}})
    state = tmp_path / "state"
    with Bus.open("router", listen=[endpoint]), Bus.open("client", connect=[endpoint]) as bus:
        node = ServerNode(bus, cfg, journal=JournalWriter(state))
        node.start()
        try:
            assert within(lambda: node._writer.busy("snapshot"), 10.0)
        finally:
            node.stop()
    assert node.journal is not None
    assert not node.journal.failures, node.journal.last_error
    assert node.journal.snapshot_s           # it was put in place
    assert list(state.glob("snapshot-*.pkl"))
