"""The offline SLAM on a log (not built yet)."""

from __future__ import annotations

from typing import Any


def run(*args: Any, **kwargs: Any) -> Any:
    raise NotImplementedError("offline SLAM on a log")
