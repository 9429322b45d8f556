"""Configuration of one robot's SLAM. One default serves every sensor and building: nothing here
is tuned to one log. Distances in metres, angles in degrees (converted where used)."""

from __future__ import annotations

from pydantic import Field

from schemas.config import ConfigModel


class ScanConfig(ConfigModel):
    """Turning ranges into points."""

    min_range_m: float = Field(0.05, gt=0)
    max_range_m: float = Field(40.0, gt=0, description="readings at or beyond: no return")
    min_point_spacing_m: float = Field(0.08, ge=0, description="thin points closer than this")
    normal_window: int = Field(2, ge=1, description="beams each side used for a normal")
    normal_max_gap_m: float = Field(0.3, gt=0, description="max neighbour distance for normals")
    no_return_free_m: float = Field(
        5.0, ge=0, description="a beam without a return marks free space up to this range "
        "(never beyond the sensor's own maximum range; 0: such beams say nothing)")


class MatcherConfig(ConfigModel):
    """Point-to-line ICP against the local map, with a correlative search as fallback."""

    enabled: bool = Field(True, description="False: odometry only (loop closure still runs)")

    max_iterations: int = Field(25, ge=1)
    converged_m: float = Field(5e-4, gt=0, description="stop when a step moves less")
    converged_deg: float = Field(0.03, gt=0)
    max_correspondence_m: float = Field(0.5, gt=0, description="first iterations")
    min_correspondence_m: float = Field(0.15, gt=0, description="last iterations")
    kernel_m: float = Field(0.05, gt=0, description="Cauchy kernel width on point-to-line")
    min_normal_cos: float = Field(0.6, ge=0, le=1)
    min_points: int = Field(30, ge=3)
    min_inlier_fraction: float = Field(0.35, ge=0, le=1)
    degenerate_eigen_ratio: float = Field(0.02, gt=0,
                                          description="λmin/λmax of the translation information")
    point_sigma_m: float = Field(0.03, gt=0, description="point-to-line noise, weighs the prior")
    use_odometry_prior: bool = True
    prior_sigma_m: float = Field(0.02, gt=0, description="odometry prediction, per scan")
    prior_sigma_per_m: float = Field(0.1, ge=0)
    prior_sigma_deg: float = Field(1.0, gt=0)
    prior_sigma_per_rad: float = Field(0.1, ge=0)
    fallback_window_m: float = Field(0.5, gt=0)
    fallback_window_deg: float = Field(45.0, gt=0)
    odometry_jump_m: float = Field(0.5, gt=0, description="larger step per scan: distrust odometry")
    odometry_jump_deg: float = Field(30.0, gt=0)


class KeyframeConfig(ConfigModel):
    distance_m: float = Field(0.5, gt=0)
    angle_deg: float = Field(20.0, gt=0)
    max_interval_s: float = Field(10.0, gt=0, description="keyframe anyway after this long")


class LocalMapConfig(ConfigModel):
    keyframes: int = Field(40, ge=1, description="recent keyframes matched against")
    voxel_m: float = Field(0.05, ge=0, description="points and normals averaged per cell")


class GraphConfig(ConfigModel):
    """Noise of the factors; sigmas in m and deg."""

    prior_sigma_m: float = Field(1e-3, gt=0)
    prior_sigma_deg: float = Field(0.05, gt=0)
    match_sigma_floor_m: float = Field(0.01, gt=0)
    match_sigma_floor_deg: float = Field(0.2, gt=0)
    match_cov_scale: float = Field(4.0, gt=0, description="ICP covariances are optimistic")
    odometry_sigma_m_per_m: float = Field(0.1, gt=0, description="fallback on odometry")
    odometry_sigma_deg_per_rad: float = Field(10.0, gt=0)
    relinearize_threshold: float = Field(0.01, gt=0)
    extra_iterations_after_loop: int = Field(3, ge=0)


class LoopClosureConfig(ConfigModel):
    enabled: bool = True
    block_keyframes: int = Field(15, ge=2, description="keyframes per loop-closure submap")
    every_keyframes: int = Field(3, ge=1, description="search on every n-th keyframe")
    query_keyframes: int = Field(5, ge=1, description="recent keyframes forming the query")
    min_graph_distance_m: float = Field(5.0, ge=0, description="skip submaps closer in the graph")
    radius_base_m: float = Field(0.5, gt=0)
    radius_per_m: float = Field(0.04, ge=0, description="drift allowance per metre travelled")
    radius_max_m: float = Field(10.0, gt=0)
    angle_base_deg: float = Field(5.0, gt=0)
    angle_per_m_deg: float = Field(0.3, ge=0)
    angle_max_deg: float = Field(30.0, gt=0)
    max_candidates: int = Field(3, ge=1)
    resolution_m: float = Field(0.1, gt=0, description="of the search; ICP refines after")
    search_voxel_m: float = Field(0.1, gt=0, description="query thinning for the search")
    submap_range_m: float = Field(20.0, gt=0, description="submap points beyond: dropped")
    min_score: float = Field(0.55, gt=0, le=1)
    min_inlier_fraction: float = Field(0.5, gt=0, le=1)
    ambiguity_ratio: float = Field(0.9, gt=0, le=1,
                                   description="reject if a distinct pose scores this × best")
    confirm_correction_m: float = Field(0.5, gt=0, description="larger jumps need a second closure")
    confirm_min_score: float = Field(0.7, gt=0, le=1, description="... and both must score this "
                                     "well (a place that repeats itself scores ~0.6 offset)")
    pending_keyframes: int = Field(40, ge=1, description="an unconfirmed closure expires after")
    confirm_tolerance_m: float = Field(0.3, gt=0)
    confirm_tolerance_deg: float = Field(3.0, gt=0)
    huber_k: float = Field(1.345, gt=0, description="robust kernel on loop factors")
    sigma_scale: float = Field(2.0, gt=0)
    max_chi2: float = Field(16.0, gt=0, description="loop factors more inconsistent: removed")


class GridConfig(ConfigModel):
    """Log-odds occupancy grid (probabilities, not log-odds, here)."""

    resolution_m: float = Field(0.05, gt=0)
    p_hit: float = Field(0.75, gt=0.5, lt=1)
    p_miss: float = Field(0.35, gt=0, lt=0.5)
    p_min: float = Field(0.12, gt=0, lt=0.5)
    p_max: float = Field(0.97, gt=0.5, lt=1)
    free_below: float = Field(0.4, gt=0, lt=1)
    occupied_above: float = Field(0.7, gt=0, lt=1)
    max_ray_m: float = Field(20.0, gt=0, description="free space is cleared up to this range")
    padding_m: float = Field(2.0, ge=0)


class SlamConfig(ConfigModel):
    """Everything ``RobotSlam`` needs."""

    scan: ScanConfig = ScanConfig()
    matcher: MatcherConfig = MatcherConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    local_map: LocalMapConfig = LocalMapConfig()
    graph: GraphConfig = GraphConfig()
    loop: LoopClosureConfig = LoopClosureConfig()
    grid: GridConfig = GridConfig()
