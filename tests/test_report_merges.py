"""The report's merge errors: the transform between two robots' start frames, as the merge
committed it and as the final joint map has it, against the simulator's truth."""

from __future__ import annotations

import math

import numpy as np

from mrslam.evaluate import compose
from mrslam.report import merge_errors

A0 = np.array([-23.0, -22.0, 0.0])      # where robots a and b started (world)
B0 = np.array([-5.0, 20.0, 0.3])


def _merge(T_joint: np.ndarray) -> dict[str, object]:
    return {"stamp_ns": 10**9, "team_id": "t-a", "joined_team_id": "t-b",
            "robots_a": ["a"], "robots_b": ["b"], "sightings": [], "T_joint": T_joint,
            "T_fused": T_joint, "T_direct_first": T_joint}


def test_final_start_frame_error_is_read_from_the_final_joint_map() -> None:
    own = {"a": A0, "b": B0}
    # truth of b's frame in a's: a's frame has yaw 0, so a translation and b's yaw
    T_true = np.array([B0[0] - A0[0], B0[1] - A0[1], B0[2]])
    off = np.array([0.3, -0.1, math.radians(2.0)])            # committed 2° and 0.3 m off
    stamps = np.array([0, 10**8])
    first_online = {"a": np.zeros(3), "b": np.array([0.01, 0.0, 0.0])}
    # in the final map, b's first pose (its online origin moved 1 cm) is 2 cm off the truth
    b_final0 = compose(T_true + np.array([0.02, 0.0, 0.0]), first_online["b"])
    final = {"a": (stamps, np.array([np.zeros(3), np.zeros(3)])),
             "b": (stamps, np.array([b_final0, b_final0]))}
    rows = merge_errors([_merge(T_true + off)], own, final, None, first_online,
                        {"a": "t-a", "b": "t-a"})
    r = rows[0]
    assert r["joint_error_m"] > 0.25 and r["joint_error_deg"] > 1.9
    assert abs(r["final_error_m"] - 0.02) < 1e-3 and r["final_error_deg"] < 1e-6
    # robots that did not end in one team have no final error
    rows = merge_errors([_merge(T_true)], own, final, None, first_online,
                        {"a": "t-a", "b": "t-b"})
    assert "final_error_m" not in rows[0] and rows[0]["joint_error_m"] < 1e-9
