"""Typed errors of the simulator."""

from __future__ import annotations


class WorldError(ValueError):
    """A world file that cannot be loaded; the message names the file and the element."""

    user_error = True


class SimError(RuntimeError):
    """The simulation cannot run as configured (unknown scenario, bad spawn, agents missing)."""

    user_error = True
