"""A compressed log decompressed once for ``slam-log``'s two passes (``KeptText``): the
second pass reads the first's bytes from memory and finds the same ranges; a log longer
than the cap, or whose stream breaks, is read again from its file."""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np

from server.offline.logs import LaserLines, read_log
from server.offline.logs.kept import KeptText
from tests.test_carmen_reader import LOG, write


def test_the_second_pass_reads_the_first_passs_text(tmp_path: Path) -> None:
    path = write(tmp_path / "log.clf.bz2", LOG)
    full = read_log(path)
    kept = KeptText()
    light = read_log(path, keep_ranges=False, kept=kept)
    assert kept.complete and kept.data is not None
    assert bytes(kept.data) == bz2.decompress(path.read_bytes())
    path.unlink()                     # the file is not read again
    lines = LaserLines(path, kept)
    for f, r in zip(full.lasers, light.lasers, strict=True):
        np.testing.assert_array_equal(lines.ranges(r), f.ranges_m)
    lines.close()
    assert kept.data is None and not kept.complete


def test_a_log_longer_than_the_cap_is_read_again_from_its_file(tmp_path: Path) -> None:
    path = write(tmp_path / "log.clf.bz2", LOG)
    full = read_log(path)
    kept = KeptText(cap=100)
    light = read_log(path, keep_ranges=False, kept=kept)
    assert not kept.complete and kept.data is None and kept.reader() is None
    lines = LaserLines(path, kept)
    for f, r in zip(full.lasers, light.lasers, strict=True):
        np.testing.assert_array_equal(lines.ranges(r), f.ranges_m)
    lines.close()


def test_a_broken_stream_is_not_kept(tmp_path: Path) -> None:
    path = tmp_path / "cut.clf.bz2"
    whole = bz2.compress((LOG * 400).encode("latin-1"))
    path.write_bytes(whole + whole[:-20])    # a second stream cut short
    kept = KeptText()
    log = read_log(path, keep_ranges=False, kept=kept)
    assert log.stats.truncated_stream
    assert not kept.complete and kept.reader() is None
