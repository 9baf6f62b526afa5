"""Evaluation metrics on hand-computable cases."""
import json

import numpy as np
import pytest

from scenesig.localiser.evaluation import (
    ReferencePath,
    blind_distances,
    coverage_metrics,
    dead_reckoning_curve,
    evaluate,
    lateral_heading_errors,
    summary,
)
from scenesig.surveys.geometry import make_pose, rot_z


def poses_xy_yaw(rows):
    return np.stack([make_pose(rot_z(np.radians(yaw)), [x, y, 0.0]) for x, y, yaw in rows])


def test_lateral_is_across_the_path_and_signed():
    path = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]])          # along +x: left is +y
    truth = poses_xy_yaw([(5, 0, 0), (12, 1, 0), (15, -2, 0)])
    est = poses_xy_yaw([(7, 0.5, 3), (11, 0.0, -2), (15, -1.5, 359)])
    lat, head, dist = lateral_heading_errors(est, truth, path)
    assert lat == pytest.approx([0.5, -1.0, 0.5])                   # along-track offsets ignored
    assert head == pytest.approx([3.0, -2.0, -1.0])                 # wrapped: 359° is -1°
    assert dist == pytest.approx([0.0, 1.0, 2.0])


def test_lateral_follows_the_path_tangent_at_the_nearest_point():
    # An L-shaped path: along x, then up y.  Left of +y is -x.
    path = np.array([[0.0, 0], [10, 0], [10, 10]])
    truth = poses_xy_yaw([(10.5, 6, 90), (3, 0.2, 0)])
    est = poses_xy_yaw([(9.5, 9, 90), (3, 0.7, 0)])
    lat, _, dist = lateral_heading_errors(est, truth, path)
    assert lat == pytest.approx([1.0, 0.5])
    assert dist == pytest.approx([0.5, 0.2])


def test_path_from_poses_and_projection():
    ref = ReferencePath(poses_xy_yaw([(0, 0, 0), (0, 0, 0), (10, 10, 45)]))   # repeated vertex dropped
    foot, left, d = ref.project(np.array([[0.0, 10.0, 3.0]]))
    assert foot[0] == pytest.approx([5.0, 5.0])
    assert left[0] == pytest.approx([-np.sqrt(0.5), np.sqrt(0.5)])
    assert d == pytest.approx([np.sqrt(50)])
    with pytest.raises(ValueError, match="2 distinct"):
        ReferencePath(np.zeros((3, 3)))


def test_summary_of_absolute_values():
    s = summary([1.0, -2.0, 3.0, -4.0, np.nan])
    assert s["median"] == 2.5 and s["mean"] == 2.5
    assert s["p95"] == pytest.approx(3.85)
    assert summary([np.nan]) == {"median": None, "mean": None, "p95": None}


def test_blind_distances():
    s = np.array([0.0, 5, 10, 15, 20])
    b = blind_distances(s, [False, True, False, False, True])
    # before the first localisation: distance from the (known) start pose
    assert b == pytest.approx([0, 0, 5, 10, 0])
    assert blind_distances(s, np.zeros(5, bool)) == pytest.approx(s)


def test_coverage_on_a_hand_example():
    # 100 m in 1 m frames; localised at 0 m, at 50 m; nothing after.
    s = np.arange(101, dtype=float)
    loc = np.zeros(101, bool)
    loc[[0, 50]] = True
    m = coverage_metrics(s, loc)
    # Within 10 m after a localisation: 0-10 and 50-60 -> 20 m of 100.
    assert m["localised_fraction"] == pytest.approx(0.20)
    # More than 20 m past the last one: 20-50 (30 m) and 70-100 (30 m).
    assert m["blind_fraction_over_20m"] == pytest.approx(0.60)
    # Rule: fail at 21 m (reset), again at 42 m; localised at 50; fail at 71 m and 92 m.
    assert m["failures"] == 4
    assert m["failures_per_km"] == pytest.approx(40.0)
    assert m["distance_m"] == 100.0
    # The pipeline's own resets override the count.
    resets = np.zeros(101, bool)
    resets[[21, 71]] = True
    assert coverage_metrics(s, loc, resets=resets)["failures"] == 2


def test_coverage_integrates_within_segments_exactly():
    # Coarse frames (every 7 m) must give the same shares as fine ones: the thresholds fall
    # inside segments and are integrated exactly.
    s = np.array([0.0, 7, 14, 21, 28, 35])
    loc = np.array([True, False, False, False, False, False])
    m = coverage_metrics(s, loc)
    assert m["localised_fraction"] == pytest.approx(10 / 35)
    assert m["blind_fraction_over_20m"] == pytest.approx(15 / 35)


def test_never_localised_run():
    s = np.linspace(0, 100, 11)
    m = coverage_metrics(s, np.zeros(11, bool))
    # only the first 10 m after the known start count as localised, all beyond 20 m as blind
    assert m["localised_fraction"] == pytest.approx(0.1) and m["blind_fraction_over_20m"] == pytest.approx(0.8)
    # 10 m frames: the count first exceeds 20 m at 30 m, restarts there, and again at 60 m and 90 m.
    assert m["failures"] == 3


def test_dead_reckoning_curve():
    s = np.arange(101, dtype=float)
    loc = np.zeros(101, bool)
    loc[[0, 50]] = True
    d = np.array([0.0, 10, 20, 49, 50, 60])
    by_distance = dead_reckoning_curve(s, loc, d)
    assert by_distance == pytest.approx([1.0, 0.8, 0.6, 0.02, 0.0, 0.0])
    assert by_distance[2] == pytest.approx(coverage_metrics(s, loc)["blind_fraction_over_20m"])
    # Stretches: 0->50 (50 m) and 50->100 (50 m).
    assert dead_reckoning_curve(s, loc, d, weighting="stretch") == pytest.approx([1, 1, 1, 1, 0, 0])
    loc2 = np.zeros(101, bool)
    loc2[[10, 20, 100]] = True                     # stretches 10, 10, 80
    assert dead_reckoning_curve(s, loc2, [5, 10, 50], weighting="stretch") == pytest.approx([1, 1 / 3, 1 / 3])
    with pytest.raises(ValueError, match="weighting"):
        dead_reckoning_curve(s, loc, d, weighting="time")


def test_evaluate_end_to_end_on_hand_trajectory():
    # Truth drives along +x at 10 m/s; the estimate is 0.3 m left, 2° off, and 1 m ahead.
    t = np.arange(0, 10.01, 0.5)
    truth = poses_xy_yaw([(10 * ti, 0, 0) for ti in t])
    est = poses_xy_yaw([(10 * ti + 1.0, 0.3, 2.0) for ti in t])
    loc = np.zeros(len(t), bool)
    loc[::4] = True                                 # every 20 m
    path = np.array([[-10.0, 0, 0], [200, 0, 0]])
    r = evaluate(t, est, t, truth, path, loc)
    m = r.metrics
    assert m["lateral_error_m"] == pytest.approx({"median": 0.3, "mean": 0.3, "p95": 0.3})
    assert m["heading_error_deg"] == pytest.approx({"median": 2.0, "mean": 2.0, "p95": 2.0})
    assert m["localised_fraction"] == pytest.approx(0.5)     # 10 of every 20 m
    assert m["blind_fraction_over_20m"] == 0.0 and m["failures"] == 0
    assert m["distance_m"] == pytest.approx(100.0)
    json.dumps(m)                                  # metrics.json-ready
    assert r.blind_m[:5] == pytest.approx([0, 5, 10, 15, 0])


def test_evaluate_interpolates_truth_and_masks_outside():
    t_truth = np.array([0.0, 1.0, 2.0])
    truth = poses_xy_yaw([(0, 0, 0), (10, 0, 0), (20, 0, 0)])
    t = np.array([0.5, 1.5, 3.0])                   # the last is past the truth
    est = poses_xy_yaw([(5, 1, 0), (15, -1, 0), (30, 5, 0)])
    r = evaluate(t, est, t_truth, truth, truth, [True, True, True])
    assert r.lateral_m[:2] == pytest.approx([1.0, -1.0]) and np.isnan(r.lateral_m[2])
    assert r.metrics["frames_evaluated"] == 2
    # Off-map frames excluded on request.
    r = evaluate(t[:2], est[:2], t_truth, truth, np.array([[0.0, 0], [10, 0]]), [True, True],
                 max_path_distance_m=1.0)
    assert r.metrics["frames_evaluated"] == 1


def test_bad_input():
    with pytest.raises(ValueError, match="non-decreasing"):
        coverage_metrics([0.0, 2.0, 1.0], [True, False, False])
    with pytest.raises(ValueError, match="equal length"):
        coverage_metrics([0.0, 1.0], [True])
    with pytest.raises(ValueError, match="N,4,4"):
        lateral_heading_errors(np.eye(4), np.eye(4), np.zeros((2, 2)))
