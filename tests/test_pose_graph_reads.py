"""``PoseGraph.poses`` read key by key (a few keys of a large graph: the local map's) gives
the poses of the whole estimate bit for bit, before and after a loop closure."""

from __future__ import annotations

import gtsam
import numpy as np

from server.slam.backend import (
    PoseGraph,
    RobotTrajectory,
    add_constraint,
    extend_trajectory,
    start_trajectory,
)


def test_a_few_keys_read_one_by_one_are_the_whole_estimates() -> None:
    g, tr = PoseGraph(), RobotTrajectory("a")
    start_trajectory(g, tr, np.zeros(3), np.array([0.01, 0.01, 0.01]))
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.02]))
    for k in range(1, 120):
        f = gtsam.BetweenFactorPose2(tr.key(k - 1), tr.key(k), gtsam.Pose2(0.3, 0.0, 0.05), noise)
        extend_trajectory(g, tr, f, "match", np.array([0.3 * k, 0.01 * k, 0.05 * k]))
    assert g.n_values == 120
    add_constraint(g, tr, gtsam.BetweenFactorPose2(tr.key(0), tr.key(119), gtsam.Pose2(
        1.0, 0.5, 0.2), noise), "loop")
    few = tr.all_keys()[-10:]
    one_by_one = g.poses(few)                 # no estimate cached: key by key
    assert g._estimate is None
    whole = g.poses(tr.all_keys())            # the whole estimate
    assert g._estimate is not None
    assert np.array_equal(one_by_one, whole[-10:])
    assert np.array_equal(g.poses(few), one_by_one)   # now from the cached estimate
