"""The server daemon's configuration (``mrslam server -c server.yaml``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from schemas.config import DEFAULT_PORT, BusConfig, ConfigModel, Coordination, Finite
from server.knownmap.config import KnownMapConfig
from server.slam.config import GridConfig, SlamConfig


class ExploreConfig(ConfigModel):
    explorer: Literal["voronoi", "frontier"] = Field(
        "voronoi", description="voronoi: targets on the skeleton of free space near frontiers; "
        "frontier: near and large frontier clusters first (a baseline)")
    lam: float = Field(1.0, ge=0.0, le=1.0, description="C = λ·d_robot + (1−λ)·d_origin")
    seek_lam: float | None = Field(
        1.0, ge=0.0, le=1.0, description="λ while robots outside the robot's team remain: "
        "nearest targets first, no pull back to the start, so robots that have not met range "
        "out sooner (null: lam throughout)")
    total_area_m2: float | None = Field(
        None, gt=0.0, description="area to cover; unknown: stop when no frontier is reachable")
    coverage_threshold: float = Field(
        0.98, gt=0.0, le=1.0, description="a team is done when its coverage reaches this share of "
        "total_area_m2")
    replan_period_s: float = Field(4.0, gt=0.0, description="re-decide the target this often")
    visited_radius_m: float = Field(1.0, gt=0.0, description="targets this close count as visited")
    unknown_as_obstacle: bool = Field(True, description="plan only through observed free space")
    frontier_view: Literal["near_end", "middle"] = Field(
        "near_end", description="Voronoi explorer, one robot deciding: look across a frontier "
        "from near its end closest to the robot, or from near its middle (teams: the middle)")


class ControlConfig(ConfigModel):
    v_mps: float = Field(0.3, gt=0.0, description="forward speed while following a path")
    omega_max_rps: float = Field(1.5, gt=0.0, description="largest turn rate commanded")
    lookahead_m: float = Field(
        1.0, gt=0.0, description="pure pursuit steers toward the path point this far ahead")
    goal_tolerance_m: float = Field(0.3, gt=0.0, description="a target this close is reached")
    robot_radius_m: float = Field(
        0.13, gt=0.0, description="the robots' radius, for clearance in planning and avoidance")
    command_ttl_s: float = Field(
        0.5, gt=0.0, le=10.0, description="each velocity command holds this long; without a newer "
        "one the robot stops")
    sighted_robot_s: float = Field(
        15.0, ge=0.0, description="after a tag sighting between two robots of different teams, "
        "each whose latest scan was narrow (slam.matcher.narrow_fov_deg) keeps clear of the "
        "other for this long, as of a teammate, placed by the other's own pose through that "
        "sighting (0: only what its scans show)")
    mapped_obstacles_m: float = Field(
        1.0, ge=0.0, description="a robot whose latest scan was narrow also avoids the occupied "
        "cells of its team's map within this distance: a wall corner beside it that its camera, "
        "turned elsewhere, has not shown lately (0: not)")
    obstacle_memory_s: float = Field(
        5.0, ge=0.0, description="a robot whose latest scan was narrow "
        "(slam.matcher.narrow_fov_deg: a depth camera's) avoids what its scans of this many "
        "seconds showed, carried along by its pose, not only what the latest one shows (0: the "
        "latest only)")
    max_scan_age_s: float = Field(
        0.5, gt=0.0, description="a scan the server gets to later than this after it was taken "
        "(the server is behind) is mapped as any other, but answered with a stop: a robot "
        "must not drive on what it saw that long ago (real time only)")
    vfh: bool = Field(
        True, description="steer around obstacles and teammates close ahead (vector field "
        "histogram)")
    stuck_window_s: float = Field(
        8.0, gt=0.0, description="a robot that moved less than stuck_min_progress_m in this long "
        "is stuck and recovers")
    stuck_min_progress_m: float = Field(0.15, gt=0.0, description="see stuck_window_s")


class TeamsConfig(ConfigModel):
    """Rendezvous, merge verification and team coordination."""

    enabled: bool = Field(True, description="False: robots never merge (each explores alone)")
    min_sightings: int = Field(3, ge=1, description="consistent sightings before a merge "
                               "(one fewer when both robots saw each other)")
    window_s: float = Field(60.0, gt=0.0, description="sightings older than this are forgotten")
    max_conflict_ratio: float = Field(0.1, ge=0.0, le=1.0, description="aligned maps may "
                                      "contradict each other in this share of wall cells")
    min_checked_cells: int = Field(40, ge=0, description="fewer wall cells in the overlap: "
                                   "the map check cannot object")
    pose_sigma_m: float = Field(0.03, gt=0.0, description="each robot's own pose uncertainty "
                                "at a sighting (weighs sightings against each other)")
    pose_sigma_deg: float = Field(0.5, gt=0.0, description="... and in heading")
    max_sighting_range_m: float = Field(2.0, gt=0.0, description="farther tag sightings are "
                                        "not used (their range is biased, their yaw unreliable)")
    narrow_far_sightings: bool = Field(
        True, description="teams with a narrow sensor (a depth camera) merge on consistent "
        "sightings from afar that no map match has confirmed, when they turn one map's "
        "square walls onto the other's within 1.5° (the narrow robot's short views seldom "
        "overlap the other team's map early)")
    max_lidar_sighting_range_m: float = Field(
        8.0, ge=0.0, description="sightings whose range and bearing the agent took from the "
        "LIDAR (located_by: lidar) are used up to this range (0: like any other)")
    sighting_tolerance_s: float = Field(0.15, gt=0.0, description="a robot's nearest scan "
                                        "must be this close to the sighting's time")
    max_pending_s: float = Field(3.0, gt=0.0, description="wait this long for the scans "
                                 "around a sighting")
    refine_period_s: float = Field(2.0, ge=0.0, description="within a team, at most one more "
                                   "rendezvous factor per robot pair this often")
    refine_on_maps: bool = Field(True, description="after a merge, match each robot's "
                                 "keyframes against the other side's map where they overlap")
    team_match_every: int = Field(2, ge=0, description="within a team, every this many new "
                                  "keyframes of a robot are matched against its teammates' "
                                  "maps where they overlap, so the joint map keeps fitting "
                                  "together as the robots go on (0: never)")
    retire_sightings_after: int = Field(3, ge=0, description="once this many map matches "
                                        "join two robots' graphs, the tag sightings between "
                                        "them leave the graph (and no more are added): the "
                                        "maps' overlap fixes the pair far more precisely, and "
                                        "the small bias one meeting's sightings share would "
                                        "bend both maps against it (0: keep them)")
    min_map_match_tries: int = Field(3, ge=1, description="where the aligned maps overlap at "
                                     "this many keyframes, at least one must match")
    map_match: bool = Field(True, description="merge two teams on their maps alone, "
                            "without a meeting, when submaps cut at several places of both "
                            "maps fit the other map under one transform and clearly more "
                            "than under any other (docs/rendezvous-and-merging.md)")
    map_match_period_s: float = Field(5.0, gt=0.0, description="one pair of teams has its "
                                      "maps matched this often (the pair waiting longest)")
    map_match_min_support: int = Field(3, ge=2, description="distinct places that must agree "
                                       "on a map-matched transform, at least two cut from "
                                       "each team's map")
    map_match_meet: bool = Field(True, description="a map-matched transform with some "
                                 "support but not enough sends a robot to where it predicts "
                                 "the other team's robot, which waits: the tags then settle "
                                 "it")
    meet_min_support: int = Field(4, ge=1, description="places that must agree on a "
                                  "transform before a meeting is planned on it (some of them "
                                  "cut from each map, and more than any rival transform has)")
    meet_max_detour_m: float = Field(25.0, gt=0.0, description="a meeting is planned only "
                                     "when the robot sent is at most this far (straight "
                                     "line) from where it predicts the other; any distance "
                                     "when the two maps joined would cover the threshold")
    meet_timeout_s: float = Field(120.0, gt=0.0, description="a planned meeting that has "
                                  "not merged the two teams after its robots' travel time "
                                  "and half a minute, or this long at most (not capped "
                                  "when the two maps joined would cover the threshold), "
                                  "refutes its transform")
    look_at_movers: bool = Field(True, description="while robots outside the team remain, "
                                 "turn toward moving things the LIDAR sees (a robot whose tag "
                                 "the forward camera would otherwise miss)")
    approach_range_m: float = Field(10.0, ge=0.0, description="a moving thing the LIDAR sees "
                                    "farther than a tag can be read, up to this range, is "
                                    "approached until its tag can be (0: never)")
    refusals_to_pause: int = Field(3, ge=0, description="two teams whose merge the maps "
                                   "refused this many times, none refusal_pause_s after the "
                                   "one before and the latest within it, stop seeking each "
                                   "other (tag calls, approaches of movers, planned "
                                   "meetings) while neither has finished: robots that keep "
                                   "reading each other's tags but cannot merge go back to "
                                   "exploring. Sightings are still tried (0: never pause)")
    refusal_pause_s: float = Field(60.0, gt=0.0, description="... that time [s]; a gap this "
                                   "long also starts the count again")
    max_map_turn_sigmas: float = Field(3.0, gt=0.0, description="a merge is refused when "
                                       "its maps, matched where they overlap, turn its "
                                       "transform by more than this many σ of its rotation, "
                                       "plus 1°")
    undo_after: int = Field(5, ge=2, description="this many consistent sightings that "
                            "contradict a committed merge undo it")
    start_poses: dict[str, tuple[Finite, Finite, Finite]] = Field(
        default_factory=dict, description="robots placed at known poses (x, y, yaw [rad]) in "
        "one common frame: they form one team from their first scan, after the map check; "
        "the others join by rendezvous")
    start_pose_sigma_m: float = Field(0.05, gt=0.0, description="how well the start poses "
                                      "are known")
    start_pose_sigma_deg: float = Field(1.0, gt=0.0, description="... and in heading")
    coordination: Coordination = Field(
        "joint", description="team targets: joint (the team's free robots assigned together "
        "on path costs, their targets kept apart) or greedy (the dissertation's rule: each "
        "robot takes its cheapest target ≥ 2 m from the others' goals); the old names optimal "
        "and thesis still work")
    sensor_weight: float = Field(
        2.0, ge=0.0, description="joint coordination: a robot's cost of a target grows by "
        "this × how much farther the nearest mapped wall is than its sensor sees, so the "
        "long-range robots take open space and the short-range ones rooms (0: off)")
    sight_spread: bool = Field(
        True, description="joint coordination in a team of unlike sensors: two robots are "
        "not sent to targets in sight of each other within the longest sensor's reach while "
        "one of them could go elsewhere (a long-range robot at either maps both)")


class DetoursConfig(ConfigModel):
    """Detours priced (server.fleet.detours): an action that takes a robot off its own
    exploration (seeking another robot, answering a call, a planned meeting, holding still to
    keep clear, a turning camera's stop) is taken only when the team's expected time saved is
    larger than what the robot's time costs it (docs/detours.md)."""

    enabled: bool = Field(False, description="price every detour and take only those worth "
                          "it (false: take every detour, and still record its price)")
    rate_window_s: float = Field(30.0, gt=0.0, description="a team's exploration rate is its "
                                 "explored area's growth over this long (and at least half "
                                 "its average since it last changed)")
    min_rate_m2_s: float = Field(0.05, gt=0.0, description="no team or robot is taken to "
                                 "explore slower than this [m²/s]")
    seek_p: float = Field(0.3, ge=0.0, le=1.0, description="the chance that turning to or "
                          "approaching something that moves merges two teams, until this "
                          "run's own seeks say otherwise")
    call_p: float = Field(0.5, ge=0.0, le=1.0, description="... answering a call")
    meeting_p: float = Field(0.6, ge=0.0, le=1.0, description="... a planned meeting")
    prior_weight: float = Field(3.0, gt=0.0, description="those chances count as this many "
                                "detours already settled")
    hold_s: float = Field(3.0, ge=0.0, description="a seek or a call ends with both robots "
                          "facing each other this long")
    outcome_window_s: float = Field(60.0, gt=0.0, description="a merge within this long after "
                                    "a detour's own time is its outcome")
    recheck_s: float = Field(15.0, gt=0.0, description="a detour declined is not priced again "
                             "for this long (the same robot, kind and other robot)")
    sweep_s: float = Field(4.0, gt=0.0, description="a turning camera's stop for a whole scan "
                           "takes this long (one turn of its tower)")
    drift_m_per_sqrt_m: float = Field(0.03, gt=0.0, description="how far a narrow sensor's "
                                      "pose drifts between whole scans, per √m driven [m]")
    tolerance_m: float = Field(0.15, gt=0.0, description="the drift a narrow sensor's map "
                               "bears before it spoils: a stop's worth is the share of this "
                               "its drift is expected to reach")
    tangle_s: float = Field(10.0, ge=0.0, description="two robots that meet head-on in a "
                            "narrow place lose about this long each (avoidance, then a stuck "
                            "robot's recovery)")


class ClockConfig(ConfigModel):
    """Time: the server's own clock, and how robots' stamps are held to it
    (server.runtime.clock)."""

    source: Literal["wall", "sim", "stamps"] = Field(
        "wall", description="the server's clock: this machine's (wall), the simulator's "
        "mrslam/sim/clock (sim; the demo), or the newest robot stamp accepted (stamps: for "
        "replaying recordings only, it trusts every robot's clock)")
    max_skew_s: float = Field(2.0, gt=0.0, description="a stamp (after its robot's re-basing) "
                              "this far ahead of its own receipt is refused until "
                              "rebase_after messages confirm that the robot's clock jumped; "
                              "re-bases larger than a tenth of this are counted as clock steps")
    rebase_after: int = Field(3, ge=1, description="this many messages in a row whose stamps "
                              "run ahead of their receipt, or go backwards, and agree on a new "
                              "offset to the server's clock re-base the robot's stamps (its "
                              "clock stepped)")
    window_s: float = Field(10.0, gt=0.0, description="a robot's offset follows the smallest "
                            "(receipt - stamp) of its messages received within this window: a "
                            "delay burst never moves it; a clock that stepped back while the "
                            "robot was silent is re-based after one window")
    tolerance_s: float = Field(0.05, ge=0.0, description="an offset within this of the "
                               "window's smallest (receipt - stamp) is left where it is (a "
                               "synchronised clock keeps offset 0)")
    step_barrier_s: float = Field(2.0, gt=0.0, description="in a lockstep simulation, wait "
                                  "this long (wall time) for every live robot's scan of a "
                                  "step, then take the step's messages in robot order, so a "
                                  "run does not depend on which message came first; a robot "
                                  "still missing is left for the next step")


class AdmissionConfig(ConfigModel):
    """Who is served: unknown robots, newcomers, robots that left (server.runtime.registry)."""

    probation_messages: int = Field(3, ge=1, description="a new robot without a liveliness "
                                    "token is admitted after this many messages (held, not "
                                    "lost, until then)")
    forget_after_s: float = Field(60.0, gt=0.0, description="robots silent and not alive for "
                                  "this long leave the registry (a robot that comes back "
                                  "starts afresh)")
    max_newcomers: int = Field(10_000, ge=1, description="ids waiting for admission at once; "
                               "beyond this the oldest waiting goes")
    newcomers_per_s: float = Field(2.0, gt=0.0, description="newcomers without a liveliness "
                                   "token are admitted at most this fast (after a burst of "
                                   "newcomer_burst); one waiting for its turn keeps only its "
                                   "latest probation_messages (robots with a token, or named "
                                   "in robots, are admitted at once)")
    newcomer_burst: int = Field(10, ge=1, description="newcomers without a token admitted at "
                                "once before newcomers_per_s applies")


class ClusterConfig(ConfigModel):
    """A server split over several worker processes, on one machine or several
    (server.runtime.cluster; docs/scale.md)."""

    worker: int | None = Field(None, ge=0, lt=64, description="this worker's number, unique "
                               "among the server's workers (0-63); null: the only server")
    handover_timeout_s: float = Field(10.0, gt=0.0, description="a worker asked for a team "
                                      "answers within this long, or the asking worker "
                                      "serves the robot afresh; two workers that both claim "
                                      "a robot for this long leave it to the lower number")


#: the server's bus, where its config says nothing else: a router on loopback (other
#: interfaces take TLS and access rules, or bus.insecure_listen)
SERVER_BUS: dict[str, Any] = {"mode": "router", "listen": [f"tcp/127.0.0.1:{DEFAULT_PORT}"],
                              "connect": []}


class ServerConfig(ConfigModel):
    bus: BusConfig = Field(default_factory=lambda: BusConfig(**SERVER_BUS))
    robots: list[str] | None = Field(
        None, description="robots allowed to join; null accepts any robot that appears")
    clock: ClockConfig = ClockConfig()
    admission: AdmissionConfig = AdmissionConfig()
    cluster: ClusterConfig = ClusterConfig()
    # one observation decides a cell for exploration: a beam through it makes it free
    # (p 0.35 < 0.4), an endpoint in it makes it occupied (p 0.75 > 0.7)
    slam: SlamConfig = SlamConfig(grid=GridConfig(p_hit=0.75, p_miss=0.35))
    explore: ExploreConfig = ExploreConfig()
    control: ControlConfig = ControlConfig()
    teams: TeamsConfig = TeamsConfig()
    detours: DetoursConfig = DetoursConfig()
    known_map: KnownMapConfig = KnownMapConfig()
    map_period_s: float = Field(
        1.0, gt=0.0, description="map updates and coverage checks, every this much scan time")
    states_period_s: float = Field(
        0.25, gt=0.0, description="robot states (poses, modes, coverage) are published this often "
        "(wall-clock time)")
    queue_per_robot: int = Field(50, ge=1, description="scans waiting beyond this are dropped")
    planner_processes: int = Field(1, ge=0, description="processes that replan robots' paths "
                                   "to their targets while the robots drive on, so the server's "
                                   "own thread only localises and steers (real time only; a "
                                   "lockstep run plans in line to stay repeatable; 0: in line)")
    out: str | None = Field(None, description="folder for maps, trajectories and the summary")
    exit_when_done: bool = Field(False, description="stop once every team has finished")
    state_dir: str | None = Field(None, description="folder of the journal of everything "
                                  "the server accepted; a server started on a folder that "
                                  "holds one resumes where it was (null: <out>/state, or no "
                                  "journal without out)")
    journal: bool = Field(True, description="keep the journal (server.runtime.journal)")
    snapshot_period_s: float = Field(5.0, gt=0.0, description="a snapshot of the server's "
                                     "state this often (wall time; longer when snapshots "
                                     "would take more than ~4 % of the CPU the server uses), "
                                     "so a restart replays only the journal since "
                                     "(server.runtime.snapshot)")
    outputs_period_s: float = Field(10.0, gt=0.0, description="maps, trajectories and the "
                                    "summary are rewritten this often while running (wall "
                                    "time; each file replaced whole), so a crash leaves the "
                                    "last good set; less often once a round would take more "
                                    "than 4 % of a core (a long mission's trajectories)")

    @model_validator(mode="before")
    @classmethod
    def _server_bus(cls, data: Any) -> Any:
        """A ``bus`` section that says only part (``insecure_listen``, ``listen``) is a
        server's: the rest comes from ``SERVER_BUS``, not from a client's defaults. With a
        ``zenoh_config`` file and no ``listen``, the file says where to listen; with
        ``insecure_listen`` and neither, the server listens on every interface."""
        if not isinstance(data, dict) or not isinstance(data.get("bus"), dict):
            return data
        given = data["bus"]
        bus = dict(given)
        bus.setdefault("mode", "router")
        if bus["mode"] != "client":
            listen = SERVER_BUS["listen"]
            if given.get("zenoh_config"):
                listen = []
            elif given.get("insecure_listen"):   # what --insecure is for: the network
                listen = [f"tcp/0.0.0.0:{DEFAULT_PORT}"]
            bus.setdefault("listen", listen)
            bus.setdefault("connect", [])
        return {**data, "bus": bus}

    @model_validator(mode="after")
    def _cluster_runs_in_real_time(self) -> ServerConfig:
        if self.cluster.worker is not None and self.clock.source == "sim":
            raise ValueError("cluster.worker: a server split over workers runs in real time "
                             "(clock.source wall); a lockstep simulation needs one server")
        return self

    def resolved_state_dir(self) -> str | None:
        """Where the journal lives, or None for no journal."""
        if not self.journal:
            return None
        if self.state_dir:
            return self.state_dir
        return str(Path(self.out) / "state") if self.out else None
