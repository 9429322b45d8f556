"""Temporary re-export of ``schemas.se2`` for the modules that still import it from here."""
# temporary: removed once server/core.py and server/teams.py import schemas.se2
from schemas.se2 import compose, inverse, transform_points

__all__ = ["compose", "inverse", "transform_points"]
