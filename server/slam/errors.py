"""Errors of the SLAM package that callers are expected to handle."""

from __future__ import annotations


class SlamInputError(ValueError):
    """A scan or odometry pose that cannot be used (non-finite, out of order, bad shape...).
    Nothing of it was accepted; the caller counts it and carries on."""

    user_error = True
