"""The base of every config model, and the Zenoh connection settings every process shares (part
of each process's config)."""

from __future__ import annotations

import logging
from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from schemas.bus import DEFAULT_MAX_MESSAGE_SIZE

log = logging.getLogger(__name__)

DEFAULT_PORT = 7447
LOOPBACK_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

#: a config number that must be finite (NaN or inf would pass a range check unnoticed)
Finite = Annotated[float, Field(allow_inf_nan=False)]

#: what the coordination modes (``server.fleet.coordination``) were called before they were named
#: for what they do: ``optimal`` was never optimal, ``thesis`` is the dissertation's greedy rule
COORDINATION_ALIASES = {"optimal": "joint", "thesis": "greedy"}


def _coordination(value: object) -> object:
    """A coordination mode's old name becomes its new one, with a note in the log."""
    new = COORDINATION_ALIASES.get(value) if isinstance(value, str) else None
    if new is None:
        return value
    log.warning("coordination %r is called %r now; the old name still works", value, new)
    return new


#: how a team's robots share out targets: ``joint`` assigns the free robots together on path
#: costs, ``greedy`` lets each take its cheapest target away from the others' goals
Coordination = Annotated[Literal["joint", "greedy"], BeforeValidator(_coordination)]


class ConfigModel(BaseModel):
    """A section of a config file: an unknown key is an error (a typo must not pass silently
    as a default)."""

    model_config = ConfigDict(extra="forbid")


class BusConfig(ConfigModel):
    """Where a process meets the bus.

    The server runs in ``router`` mode and ``listen``s; everyone else is a ``client`` that
    ``connect``s. ``zenoh_config`` names a json5 file (TLS, access control, credentials) that the
    settings here are applied on top of.

    A router or peer that would listen beyond this machine without TLS and access control
    (see ``schemas.bus.listen_security``) is refused unless ``insecure_listen`` is set; to tell,
    its ``zenoh_config`` is read here. A client's is read when its session opens (a config may
    be validated on another machine than the one it is for).
    """

    mode: Literal["router", "client", "peer"] = Field(
        "client", description="router: others connect to it (the server); client: connects to a "
        "router (everyone else); peer: both, without a router")
    listen: list[str] = Field(
        default_factory=list, description="endpoints a router or peer listens on, e.g. "
        "tcp/127.0.0.1:7447 (beyond loopback only with TLS and access rules, or insecure_listen)")
    connect: list[str] = Field(
        default_factory=lambda: [LOOPBACK_ENDPOINT], description="router endpoints to connect to, "
        "e.g. tcp/10.0.0.2:7447")
    zenoh_config: str | None = Field(
        None, description="a Zenoh json5 file (TLS, access control, credentials); the settings "
        "here are applied on top of it")
    connect_timeout_ms: int | None = Field(
        default=None, description="-1 waits for the router forever; null keeps Zenoh's default")
    insecure_listen: bool = Field(
        False, description="listen on other machines' reach without TLS and access control "
        "(logged as a warning at every start); otherwise such a config is refused")
    max_message_size: int = Field(
        DEFAULT_MAX_MESSAGE_SIZE, ge=65_536, le=1 << 30, description="larger messages are "
        "dropped where they arrive [bytes]; above the largest camera frame and map")

    @model_validator(mode="after")
    def _secured_or_local(self) -> BusConfig:
        if self.mode == "client" or self.insecure_listen:
            return self
        from schemas.bus import BusError, is_loopback_endpoint, listen_security, zenoh_config

        if self.listen and not self.zenoh_config and all(map(is_loopback_endpoint, self.listen)):
            return self   # the usual case, decided without loading Zenoh
        try:
            conf = zenoh_config(self.mode, self.listen, (), self.zenoh_config)
        except BusError as e:
            raise ValueError(str(e)) from None
        sec = listen_security(conf)
        if not sec.secure:
            raise ValueError(
                f"would listen on {', '.join(sec.exposed)} without {' and '.join(sec.missing)}: "
                "listen on loopback only (tcp/127.0.0.1:<port>), or configure TLS and access "
                "rules in bus.zenoh_config (deploy/README.md), or accept the risk with "
                "bus.insecure_listen: true (mrslam server --insecure)")
        return self
