"""The relation evaluation (not built yet)."""

from __future__ import annotations

from typing import Any


def run(*args: Any, **kwargs: Any) -> Any:
    raise NotImplementedError("relation evaluation")
