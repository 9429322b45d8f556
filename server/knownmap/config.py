"""The configuration of a mission on a known map (``known_map`` in the server's YAML)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from schemas.config import ConfigModel

MapMode = Literal["localize", "extend"]


class KnownMapConfig(ConfigModel):
    """Starting from a map a previous mission made (docs/known-map.md)."""

    path: str | None = Field(
        None, description="a previous mission's map: its run folder, its server folder, its "
        "state folder or a known_map folder (null: start from nothing, as always)")
    site: str | None = Field(
        None, description="the building's name, written with the map this server leaves; a "
        "map written for another site is refused (the demo sets the world's name)")
    mode: MapMode = Field(
        "localize", description="localize: the map stays as it is and robots only localise "
        "in it; extend: what the robots see is mapped into it, as a continuation of the "
        "mission that made it")
    query_period_s: float = Field(
        1.0, gt=0.0, description="a robot not yet placed has its map matched against the "
        "known map this often")
    window_m: float = Field(
        14.0, gt=0.0, description="side of the square of a searching robot's map matched "
        "against the known map, around each of its places")
    clear_ratio: float = Field(
        0.8, gt=0.0, lt=1.0, description="a placement wins a query only when every other "
        "placement that fits (acceptance index 0.9 or more) scores at most this share of it")
    confirmations: int = Field(
        2, ge=1, description="queries in a row a placement must win before it is checked "
        "on the maps and the robot placed")
    lost_conflict_ratio: float = Field(
        0.3, gt=0.0, le=1.0, description="a placed robot's scan disagrees with the map when "
        "more than this share of its returns on mapped ground fall in open space (a placed "
        "robot's scans: 0.01-0.13, among closed doors and moved boxes too; a robot carried "
        "5 m: 0.45-0.97)")
    lost_after_s: float = Field(
        1.5, gt=0.0, description="a placed robot whose scans disagree with the map this long "
        "without a break is lost: it leaves the map's team and is placed again")
    supersede_m: float = Field(
        1.5, ge=0.0, description="extend: a map keyframe this close to a new keyframe whose "
        "beams reach 80 % of its returns is retired, the newer view replacing it "
        "(server/knownmap/changes.py; 0: never)")
    change_votes: int = Field(
        2, ge=1, description="extend: keyframes that must see a cell differ from the map (a "
        "return in its open space, or a beam well past one of its returns) before the "
        "map's views that contradict the change are retired")
    inspect: bool = Field(
        True, description="extend: placed robots first pass over the map, each sent to the "
        "place of the map's keyframes with most places no robot of this mission has come "
        "within 1.5 m of around it (3 m), for the way there, before they explore what is "
        "unknown")
    inspected_share: float = Field(
        0.95, gt=0.0, le=1.0, description="extend: the pass is over when this share of "
        "what the map's older keyframes saw (0.25 m cells of their returns) has been seen again "
        "by this mission's beams, or when no place is left worth going to")
