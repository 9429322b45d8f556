"""The stable device path of a fake: a symlink moved onto a new pseudo-terminal at once."""

from __future__ import annotations

import os
from pathlib import Path


def point_link(link: Path, slave_fd: int) -> None:
    """Make ``link`` name the pseudo-terminal ``slave_fd`` (replaced atomically, as udev
    would when a device is plugged in again)."""
    tmp = link.with_suffix(".new")
    tmp.unlink(missing_ok=True)
    tmp.symlink_to(os.ttyname(slave_fd))
    tmp.replace(link)
