"""The Zenoh connection settings every process shares (part of each process's config)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

DEFAULT_PORT = 7447


class BusConfig(BaseModel):
    """Where a process meets the bus.

    The server runs in ``router`` mode and ``listen``s; everyone else is a ``client`` that
    ``connect``s. ``zenoh_config`` names a json5 file (TLS, access control, credentials) that the
    settings here are applied on top of.
    """

    model_config = ConfigDict(extra="forbid")

    mode: Literal["router", "client", "peer"] = "client"
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=lambda: [f"tcp/127.0.0.1:{DEFAULT_PORT}"])
    zenoh_config: str | None = None
    connect_timeout_ms: int | None = Field(
        default=None, description="-1 waits for the router forever; None keeps Zenoh's default")
