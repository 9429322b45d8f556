from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def endpoint() -> str:
    from schemas.bus import free_local_endpoint

    return free_local_endpoint()


@pytest.fixture
def router(endpoint: str) -> Iterator[object]:
    from schemas.bus import Bus

    with Bus.open("router", listen=[endpoint]) as bus:
        yield bus
