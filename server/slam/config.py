"""Configuration of one robot's SLAM. One default serves every sensor and building: nothing here
is tuned to one log. Distances in metres, angles in degrees (converted where used)."""

from __future__ import annotations

from pydantic import Field

from schemas.config import ConfigModel
from schemas.occupancy import FREE_BELOW, OCCUPIED, OCCUPIED_ABOVE


class ScanConfig(ConfigModel):
    """Turning ranges into points."""

    min_range_m: float = Field(
        0.05, gt=0, description="readings closer than this are dropped (the robot's own body, "
        "noise)")
    max_range_m: float = Field(40.0, gt=0, description="readings at or beyond: no return")
    min_point_spacing_m: float = Field(0.08, ge=0, description="thin points closer than this")
    normal_window: int = Field(2, ge=1, description="beams each side used for a normal")
    narrow_normal_window: int = Field(
        4, ge=1, description="... in a narrow scan (matcher.narrow_fov_deg): a depth camera's "
        "beams lie closer together and its depth is noisier")
    normal_max_gap_m: float = Field(0.3, gt=0, description="max neighbour distance for normals")
    no_return_free_m: float = Field(
        5.0, ge=0, description="a beam without a return marks free space up to this range "
        "(never beyond the sensor's own maximum range; 0: such beams say nothing)")


class MatcherConfig(ConfigModel):
    """Point-to-line ICP against the local map, with a correlative search as fallback."""

    enabled: bool = Field(True, description="False: odometry only (loop closure still runs)")

    max_iterations: int = Field(25, ge=1, description="ICP iterations at most per match")
    converged_m: float = Field(5e-4, gt=0, description="stop when a step moves less")
    converged_deg: float = Field(0.03, gt=0, description="stop when a step turns less")
    max_correspondence_m: float = Field(0.5, gt=0, description="first iterations")
    min_correspondence_m: float = Field(0.15, gt=0, description="last iterations")
    kernel_m: float = Field(0.05, gt=0, description="Cauchy kernel width on point-to-line")
    min_normal_cos: float = Field(
        0.6, ge=0, le=1, description="a scan point pairs with a map line only when their normals "
        "differ by less than acos of this")
    min_points: int = Field(
        30, ge=3, description="fewer points in the scan or the local map: no match, odometry only")
    min_inlier_fraction: float = Field(
        0.35, ge=0, le=1, description="a match with fewer inliers tries the correlative search, "
        "then falls back on odometry")
    degenerate_eigen_ratio: float = Field(0.02, gt=0,
                                          description="λmin/λmax of the translation information")
    point_sigma_m: float = Field(0.03, gt=0, description="point-to-line noise, weighs the prior")
    use_odometry_prior: bool = Field(
        True, description="weigh the odometry prediction in the match (ignored when odometry "
        "jumped)")
    prior_sigma_m: float = Field(0.02, gt=0, description="odometry prediction, per scan")
    prior_sigma_per_m: float = Field(
        0.1, ge=0, description="σ of the prediction grows by this per metre of the step [m/m]")
    prior_sigma_deg: float = Field(1.0, gt=0, description="σ of the prediction's heading per scan")
    prior_sigma_per_rad: float = Field(
        0.1, ge=0, description="heading σ grows by this per radian turned [rad/rad]")
    fallback_window_m: float = Field(
        0.5, gt=0, description="half-width of the correlative search around the last pose")
    fallback_window_deg: float = Field(
        45.0, gt=0, description="half-angle of the correlative search")
    narrow_fov_deg: float = Field(
        180.0, gt=0, le=360, description="a scan spanning less is narrow (a depth camera's): "
        "it gets no correlative search, as it holds too little of a place to tell it from one "
        "nearby, and needs only narrow_min_points")
    narrow_min_normal_cos: float = Field(
        0.8, ge=0, le=1, description="min_normal_cos for a narrow scan: with a few metres of "
        "wall in view, a pairing across a corner pulls the pose further")
    narrow_min_points: int = Field(
        10, ge=3, description="min_points for a narrow scan (a depth camera sees a few metres "
        "of wall)")
    narrow_prior_sigma_m: float = Field(
        0.01, gt=0, description="prior_sigma_m for a narrow scan: its match pins the pose "
        "less well than a 360° scan's, so the prediction counts for more")
    narrow_prior_sigma_deg: float = Field(
        0.3, gt=0, description="prior_sigma_deg for a narrow scan")
    narrow_smoothing: int = Field(
        10, ge=1, description="a narrow scan's pose averages the latest this many matches, "
        "each carried to it by odometry and weighed by its information (1: its own match)")
    odometry_jump_m: float = Field(0.5, gt=0, description="larger step per scan: distrust odometry")
    odometry_jump_deg: float = Field(
        30.0, gt=0, description="larger turn per scan: distrust odometry")


class KeyframeConfig(ConfigModel):
    distance_m: float = Field(0.5, gt=0, description="a new keyframe after moving this far")
    angle_deg: float = Field(20.0, gt=0, description="... or after turning this much")
    max_interval_s: float = Field(10.0, gt=0, description="keyframe anyway after this long")
    novel_fraction: float = Field(
        0.3, gt=0, le=1, description="a narrow scan (matcher.narrow_fov_deg) becomes a keyframe "
        "also when this share of its points is new to the local map, so a sensor that looks "
        "one way at a time (a depth camera turned on a tower) maps what it sees")
    novel_m: float = Field(0.3, gt=0, description="... a point is new farther than this from "
                           "every local map point")
    reuse: bool = Field(True, description=(
        "once the robot's team has explored its area (the server's robots only), a scan "
        "where a keyframe already is re-anchors the robot on that keyframe instead of adding "
        "one, so memory stays flat while robots drive over mapped ground"))
    reuse_m: float = Field(0.4, gt=0, description="... within this distance of the keyframe")
    reuse_deg: float = Field(180.0, gt=0, le=180.0, description=(
        "... and this heading (180: any, as a 360° scanner sees the same from every heading)"))
    render_on_disk: bool = Field(True, description=(
        "keep what only drawing the map needs (every return of a keyframe, single precision) "
        "in an unlinked file in MRSLAM_RENDER_DIR, the server's state folder or the temporary "
        "folder instead of in memory; off: in memory"))


class LocalMapConfig(ConfigModel):
    keyframes: int = Field(40, ge=1, description="recent keyframes matched against")
    narrow_keyframes: int = Field(
        150, ge=1, description="... by a narrow sensor (matcher.narrow_fov_deg), which takes "
        "keyframes far more often for the little each shows")
    voxel_m: float = Field(0.05, ge=0, description="points and normals averaged per cell")
    guide_radius_m: float = Field(
        6.0, ge=0, description="a narrow sensor's robot in a team also matches against its "
        "teammates' keyframes within this distance, their walls in place of its own where "
        "both have one (0: its own only)")


class GraphConfig(ConfigModel):
    """Noise of the factors; sigmas in m and deg."""

    prior_sigma_m: float = Field(1e-3, gt=0, description="σ of the prior on the first pose")
    prior_sigma_deg: float = Field(0.05, gt=0, description="σ of the prior's heading")
    match_sigma_floor_m: float = Field(
        0.01, gt=0, description="scan-match factors are never more certain than this")
    match_sigma_floor_deg: float = Field(0.2, gt=0, description="... nor than this in heading")
    match_cov_scale: float = Field(4.0, gt=0, description="ICP covariances are optimistic")
    odometry_sigma_m_per_m: float = Field(0.1, gt=0, description="fallback on odometry")
    odometry_sigma_deg_per_rad: float = Field(
        10.0, gt=0, description="heading σ of an odometry factor per radian turned")
    relinearize_threshold: float = Field(
        0.01, gt=0, description="ISAM2 relinearises variables that moved more than this")
    extra_iterations_after_loop: int = Field(
        3, ge=0, description="ISAM2 updates run after a loop closure or map match is added")


class LoopClosureConfig(ConfigModel):
    enabled: bool = Field(True, description="False: no loop closure")
    block_keyframes: int = Field(15, ge=2, description="keyframes per loop-closure submap")
    every_keyframes: int = Field(3, ge=1, description="search on every n-th keyframe")
    query_keyframes: int = Field(5, ge=1, description="recent keyframes forming the query")
    min_graph_distance_m: float = Field(5.0, ge=0, description="skip submaps closer in the graph")
    radius_base_m: float = Field(
        0.5, gt=0, description="search radius around the estimate for a submap next to the robot "
        "in the graph")
    radius_per_m: float = Field(0.04, ge=0, description="drift allowance per metre travelled")
    radius_max_m: float = Field(10.0, gt=0, description="largest search radius")
    angle_base_deg: float = Field(
        5.0, gt=0, description="search half-angle for a submap next to the robot in the graph")
    angle_per_m_deg: float = Field(
        0.3, ge=0, description="drift allowance in heading per metre travelled")
    angle_max_deg: float = Field(30.0, gt=0, description="largest search half-angle")
    narrow_radius_max_m: float = Field(
        1.5, gt=0, description="largest search radius for a narrow sensor's keyframes "
        "(matcher.narrow_fov_deg): a few metres of wall in view cannot tell a place from one "
        "a door further on, and larger windows let such false closures in")
    narrow_angle_max_deg: float = Field(10.0, gt=0, description="... and half-angle")
    max_candidates: int = Field(3, ge=1, description="submaps searched per query, nearest first")
    resolution_m: float = Field(0.1, gt=0, description="of the search; ICP refines after")
    search_voxel_m: float = Field(0.1, gt=0, description="query thinning for the search")
    submap_range_m: float = Field(20.0, gt=0, description="submap points beyond: dropped")
    min_score: float = Field(
        0.55, gt=0, le=1, description="correlative search score a candidate needs")
    min_inlier_fraction: float = Field(
        0.5, gt=0, le=1, description="the refining ICP needs this share of inliers")
    ambiguity_ratio: float = Field(0.9, gt=0, le=1,
                                   description="reject if a distinct pose scores this × best")
    confirm_correction_m: float = Field(0.5, gt=0, description="larger jumps need a second closure")
    confirm_min_score: float = Field(0.7, gt=0, le=1, description="... and both must score this "
                                     "well (a place that repeats itself scores ~0.6 offset)")
    pending_keyframes: int = Field(40, ge=1, description="an unconfirmed closure expires after")
    confirm_tolerance_m: float = Field(
        0.3, gt=0, description="two closures agree when their corrections differ by less than "
        "this")
    confirm_tolerance_deg: float = Field(3.0, gt=0, description="... and this in heading")
    huber_k: float = Field(1.345, gt=0, description="robust kernel on loop factors")
    sigma_scale: float = Field(2.0, gt=0, description="loop factors' σ are the match's times this")
    max_chi2: float = Field(16.0, gt=0, description="loop factors more inconsistent: removed")


class SquareWallsConfig(ConfigModel):
    """Headings held by square walls (``server.slam.heading``): where a robot's keyframes show
    walls along two perpendicular directions, each such keyframe's heading is tied, modulo
    90°, to earlier such keyframes' (the first and others spread over the run)."""

    enabled: bool = Field(True, description="False: never")
    narrow_only: bool = Field(
        True, description="only for a narrow sensor (matcher.narrow_fov_deg), whose heading "
        "drifts where it sees a few metres of wall; a 360° scan holds its own")
    min_points: int = Field(20, ge=3, description="points with a normal a keyframe needs")
    min_alignment: float = Field(
        0.85, gt=0, le=1, description="a keyframe's normals must lie this close to one square "
        "grid (|mean(exp(4iα))|; 1: all on it)")
    agree_deg: float = Field(
        3.0, gt=0, description="a keyframe agrees with the rule when its walls put its heading "
        "within this of the estimate; and is tied to the reference (a whole scan at the start: "
        "slam.sweep) only then")
    min_checked: int = Field(10, ge=1, description="keyframes checked before the rule is used")
    min_agreement: float = Field(
        0.7, gt=0, le=1, description="... of which this share must agree (walls that are not "
        "square agree by chance about one time in fifteen)")
    max_correction_deg: float = Field(
        8.0, gt=0, lt=45, description="a keyframe whose walls say more is not tied (a wall off "
        "the square grid)")
    partners: int = Field(
        4, ge=1, description="earlier keyframes a keyframe is tied to: the first that saw "
        "square walls and others spread over the run")
    sigma_deg: float = Field(
        1.0, gt=0, description="σ of a keyframe's ties in heading, taken together")
    huber_k: float = Field(1.345, gt=0, description="robust kernel on the tie")


class SweepConfig(ConfigModel):
    """Whole scans of a turning camera (``server.slam.sweep``): a robot whose camera turns on
    a tower stands still every ``every_m`` of driving while the camera turns once round, and
    the views of that turn are matched as one 360° scan."""

    enabled: bool = Field(True, description="False: never stop for one")
    every_m: float = Field(
        1.0, gt=0, description="odometry distance driven between two whole scans")
    wait_s: float = Field(
        6.0, gt=0, description="the robot drives on when no whole scan has come after standing "
        "still this long")
    coverage: float = Field(
        0.9, gt=0, le=1, description="share of the circle the views must cover")
    still_m: float = Field(
        0.005, gt=0, description="the views since the odometry moved less than this are one scan")
    still_deg: float = Field(0.5, gt=0, description="... and turned less than this")
    max_shift_m: float = Field(
        0.05, gt=0, description="a whole scan's match against the one before is refused when it "
        "moves the pose further from the odometry's than this (over a metre, wheel odometry "
        "is good to a centimetre or two; a wall matched to the wrong one is off by more)")
    max_turn_deg: float = Field(3.0, gt=0, description="... or turns it more than this")


class GridConfig(ConfigModel):
    """Log-odds occupancy grid (probabilities, not log-odds, here)."""

    resolution_m: float = Field(0.05, gt=0, description="cell size")
    p_hit: float = Field(
        0.75, gt=0.5, lt=1, description="occupancy probability a beam's endpoint gives its cell")
    p_miss: float = Field(
        0.35, gt=0, lt=0.5, description="occupancy probability a beam gives the cells it passes "
        "through")
    p_min: float = Field(
        0.12, gt=0, lt=0.5, description="log-odds are clamped to this probability from below, so "
        "the map stays revisable")
    p_max: float = Field(0.97, gt=0.5, lt=1, description="... and to this from above")
    free_below: float = Field(
        FREE_BELOW / OCCUPIED, gt=0, lt=1,
        description="cells less likely occupied than this are free")
    occupied_above: float = Field(
        OCCUPIED_ABOVE / OCCUPIED, gt=0, lt=1,
        description="cells more likely occupied than this are occupied")
    max_ray_m: float = Field(20.0, gt=0, description="free space is cleared up to this range")
    padding_m: float = Field(2.0, ge=0, description="unknown margin kept around the mapped area")


class SlamConfig(ConfigModel):
    """Everything ``RobotSlam`` needs."""

    scan: ScanConfig = ScanConfig()
    matcher: MatcherConfig = MatcherConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    local_map: LocalMapConfig = LocalMapConfig()
    graph: GraphConfig = GraphConfig()
    loop: LoopClosureConfig = LoopClosureConfig()
    square_walls: SquareWallsConfig = SquareWallsConfig()
    sweep: SweepConfig = SweepConfig()
    grid: GridConfig = GridConfig()
