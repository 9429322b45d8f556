"""Front-end: match a scan against the local map, starting from the odometry prediction, and
decide how far to trust the result.

Order of attempts: point-to-line ICP from the prediction (plus, when the odometry step looks
implausible, from a constant-velocity and a standstill guess); if no attempt explains enough of
the scan, a correlative search in a wide window around the last pose (not for a narrow scan,
which holds too little of the place to pick the right pose in such a window); if that fails
too, the odometry prediction. A match that is degenerate (a featureless corridor) keeps its result
across the corridor and takes the odometry along it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose, pose_distance
from server.slam.config import MatcherConfig
from server.slam.correlative import LikelihoodField, search
from server.slam.icp import IcpParams, MatchResult, PointMap, icp
from server.slam.scan import ScanPoints

F64 = NDArray[np.float64]


class MatchKind(Enum):
    ICP = "icp"
    DEGENERATE = "degenerate"
    CORRELATIVE = "correlative"
    ODOMETRY = "odometry"


@dataclass(frozen=True)
class FrontendMatch:
    """The pose chosen for a scan, how it was obtained, and its information (map frame)."""

    T_map_robot: F64
    kind: MatchKind
    information: F64
    inlier_fraction: float


def icp_params(cfg: MatcherConfig) -> IcpParams:
    return IcpParams(max_iterations=cfg.max_iterations,
                     max_correspondence_m=cfg.max_correspondence_m,
                     min_correspondence_m=cfg.min_correspondence_m, kernel_m=cfg.kernel_m,
                     min_normal_cos=cfg.min_normal_cos,
                     degenerate_eigen_ratio=cfg.degenerate_eigen_ratio,
                     point_sigma_m=cfg.point_sigma_m, converged_m=cfg.converged_m,
                     converged_rad=math.radians(cfg.converged_deg))


def is_narrow(scan: ScanPoints, cfg: MatcherConfig) -> bool:
    """A scan of a sensor that sees less than ``narrow_fov_deg`` (a depth camera's)."""
    return scan.fov_rad < math.radians(cfg.narrow_fov_deg)


def min_points(scan: ScanPoints, cfg: MatcherConfig) -> int:
    """Points a scan needs to be matched."""
    return cfg.narrow_min_points if is_narrow(scan, cfg) else cfg.min_points


def odometry_step_suspicious(step: F64, cfg: MatcherConfig) -> bool:
    d, a = pose_distance(step)
    return d > cfg.odometry_jump_m or a > math.radians(cfg.odometry_jump_deg)


def along_odometry(res: MatchResult, T_pred: F64) -> F64:
    """The match with its translation along the degenerate direction v taken from the
    prediction: t = t_icp + v vᵀ (t_pred − t_icp)."""
    assert res.degenerate_dir is not None
    v = res.degenerate_dir
    T = res.T_map_scan.copy()
    T[:2] += v * float(v @ (T_pred[:2] - T[:2]))
    return T


def odometry_prior(step: F64, cfg: MatcherConfig, narrow: bool = False) -> F64:
    """Information (3×3) of the odometry prediction of one scan step: σ grows with the step
    (from a smaller base for a narrow scan's)."""
    d, a = pose_distance(step)
    base_m, base_deg = ((cfg.narrow_prior_sigma_m, cfg.narrow_prior_sigma_deg) if narrow
                        else (cfg.prior_sigma_m, cfg.prior_sigma_deg))
    s_xy = base_m + cfg.prior_sigma_per_m * d
    s_th = math.radians(base_deg) + cfg.prior_sigma_per_rad * a
    return np.diag([s_xy ** -2, s_xy ** -2, s_th ** -2])


def match_scan(scan: ScanPoints, target: PointMap, T_pred: F64, T_last: F64,
               T_step_velocity: F64, odometry_suspicious: bool, cfg: MatcherConfig,
               params: IcpParams, prior_info: F64 | None = None) -> FrontendMatch:
    """Pose of ``scan`` in the frame of ``target``; see the module docstring. ``prior_info``
    weighs the odometry prediction in the match (ignored when the odometry step is
    suspicious)."""
    pts = scan.points
    nrm = scan.normals
    n_min = min_points(scan, cfg)
    if len(pts) < n_min or len(target) < cfg.min_points or not cfg.enabled:
        return FrontendMatch(T_pred, MatchKind.ODOMETRY, np.zeros((3, 3)), 0.0)
    guesses = [T_pred]
    prior: F64 | None = prior_info
    if odometry_suspicious:
        guesses += [compose(T_last, T_step_velocity), T_last]
        prior = None
    best: MatchResult | None = None
    for g in guesses:
        res = icp(pts, nrm, target, g, params, prior)
        if best is None or res.inlier_fraction > best.inlier_fraction:
            best = res
    assert best is not None
    kind = MatchKind.ICP
    if best.inlier_fraction < cfg.min_inlier_fraction and not is_narrow(scan, cfg):
        field = LikelihoodField(target.points, 0.1, sigma_m=0.1, margin_m=cfg.fallback_window_m,
                                levels=4)
        coarse = search(field, pts, T_last, cfg.fallback_window_m,
                        math.radians(cfg.fallback_window_deg), min_score=0.3)
        if coarse is not None:
            res = icp(pts, nrm, target, coarse.T_map_scan, params)
            if res.inlier_fraction > best.inlier_fraction:
                best, kind = res, MatchKind.CORRELATIVE
    if best.inlier_fraction < cfg.min_inlier_fraction:
        return FrontendMatch(T_pred, MatchKind.ODOMETRY, np.zeros((3, 3)), best.inlier_fraction)
    if best.degenerate:
        return FrontendMatch(along_odometry(best, T_pred), MatchKind.DEGENERATE,
                             best.information, best.inlier_fraction)
    return FrontendMatch(best.T_map_scan, kind, best.information, best.inlier_fraction)


def match_step(scan: ScanPoints, target: PointMap, T_pred: F64, T_last: F64,
               T_step_velocity: F64, T_step_odom: F64, cfg: MatcherConfig, params: IcpParams,
               narrow: bool = False) -> FrontendMatch:
    """``match_scan`` for a scan one odometry step ``T_step_odom`` after the last, with that
    step's prior (a narrow sensor's, from its smaller base, when ``narrow``) if
    ``use_odometry_prior``."""
    prior = odometry_prior(T_step_odom, cfg, narrow) if cfg.use_odometry_prior else None
    return match_scan(scan, target, T_pred, T_last, T_step_velocity,
                      odometry_step_suspicious(T_step_odom, cfg), cfg, params, prior)
