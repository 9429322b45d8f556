"""Gathering the server's memory into huge pages after each snapshot child (fork copies fewer
page tables): the regions chosen, and the kernel really doing it where it can."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.runtime.hugepages import HUGE, Collapser, anonymous_ranges, kernel_version

MAPS = """\
55d0c2a00000-55d0c2a21000 r--p 00000000 08:01 123  /usr/bin/python3.11
55d0c4000000-55d0c4a00000 rw-p 00000000 00:00 0    [heap]
7f0000100000-7f0000700000 rw-p 00000000 00:00 0
7f0000800000-7f0000900000 rw-p 00000000 00:00 0
7f0001000000-7f0001400000 rw-s 00000000 00:01 77   /dev/zero (deleted)
7f0002000000-7f0002400000 rw-p 00000000 08:01 99   /usr/lib/libfoo.so
7f0003000000-7f0003400000 r--p 00000000 00:00 0
7ffd1c000000-7ffd1c600000 rw-p 00000000 00:00 0    [stack]
"""


def test_only_private_writable_anonymous_regions_are_chosen_in_whole_huge_pages() -> None:
    got = anonymous_ranges(MAPS)
    # the heap whole (10 MB, aligned), the 6 MB anonymous region cut to its aligned 4 MB;
    # the 1 MB region, shared memory, a library's data, read-only memory and the stack left
    assert got == [(0x55D0C4000000, 0xA00000), (0x7F0000200000, 0x400000)]
    assert all(start % HUGE == 0 and length % HUGE == 0 for start, length in got)


def test_kernel_versions_are_read_from_release_strings() -> None:
    assert kernel_version("6.18.44-fc-v782") == (6, 18)
    assert kernel_version("5.15.0-91-generic") == (5, 15)
    assert kernel_version("weird") == (0, 0)


def _anon_huge_kb() -> int:
    for line in Path("/proc/self/smaps_rollup").read_text().splitlines():
        if line.startswith("AnonHugePages:"):
            return int(line.split()[1])
    return 0


def test_the_kernel_gathers_written_memory_into_huge_pages() -> None:
    pages = Collapser()
    if pages.unavailable:
        pytest.skip(pages.unavailable)
    block = bytearray(64 << 20)            # malloc'd, written page by page: small pages
    block[::4096] = b"\x01" * len(block[::4096])
    before = _anon_huge_kb()
    assert pages.collapse() > 0.0 and pages.runs == 1
    assert _anon_huge_kb() - before >= 32 << 10, "less than half the block in huge pages"
    assert block[4096] == 1 and block[4097] == 0      # contents kept
