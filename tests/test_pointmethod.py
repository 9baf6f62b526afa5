"""ORB/SIFT weak localiser: the image-only stage (``prepare``) that the replay runs ahead on a worker."""
import numpy as np
import pytest
from point_world import CAMERA, T_VC, camera_pose, render, vehicle_pose
from test_pointmap import keyframe_map, point_store, world  # noqa: F401  (module fixtures)

from scenesig.localiser.pipeline import MotionPrior, make_method
from scenesig.localiser.pointmethod import LiveFrame
from scenesig.localiser.solver import pose_exp


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_prepared_frame_gives_the_same_observation_and_counts_its_time(point_store, world, kind):  # noqa: F811
    store, T_wp0 = point_store
    T_pv = vehicle_pose(3.0, 0.8, np.radians(2.0))
    live, _ = render(camera_pose(T_pv), world)
    method = make_method(kind, store, CAMERA, T_VC)
    P = np.diag([0.01, 0.01, 0.03, 1.0, 1.0, 0.3]) ** 2
    prior = MotionPrior(0.0, T_wp0 @ T_pv @ pose_exp([0.005, -0.005, 0.02, 0.5, -0.4, 0.1]), P, 0, T_wp0, 1,
                        False, 0.0)
    frame = method.prepare(live)
    assert isinstance(frame, LiveFrame) and frame.shape == live.shape[:2] and frame.ms > 0
    assert method.prepare(frame) is frame                     # already prepared: passed through
    a, b = method.detect(live, 0, prior), method.detect(frame, 0, prior)
    assert len(a) >= 30
    for f in ("uv", "R", "xyz", "map_index"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert b.ms >= frame.ms                                   # the extraction is part of detection
    ma, mb = method.solve(a, 0, prior), method.solve(b, 0, prior)
    np.testing.assert_array_equal(ma.constraint.T_world_vehicle, mb.constraint.T_world_vehicle)
    with pytest.raises(ValueError, match="camera"):
        method.prepare(live[:100])


def test_shared_live_features_give_the_same_observation(point_store, world):  # noqa: F811
    """Inside a feature-cache block, a second ORB localiser (as ``orb-all`` after ``orb``) takes the live
    features the first extracted: the same detections."""
    from scenesig.signatures.pointfeatures import feature_cache

    store, T_wp0 = point_store
    live, _ = render(camera_pose(vehicle_pose(3.0, 0.8, np.radians(2.0))), world)
    configs = (None, {"match": "dapc"})
    alone = [make_method("orb", store, CAMERA, T_VC, c).detect(live, 0, None) for c in configs]
    with feature_cache() as cache:
        shared = [make_method("orb", store, CAMERA, T_VC, c).detect(live, 0, None) for c in configs]
    assert (cache.misses, cache.hits) == (1, 1)
    for a, b in zip(alone, shared):
        assert len(a) >= 30
        for f in ("uv", "R", "xyz", "map_index"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_command_line_method_options():
    from scenesig.localiser.replay import method_options

    assert method_options("orb") == {}
    assert method_options("sift", match="gms", point_map="all", prior_gating=False) == \
        {"match": "gms", "point_map": "all", "prior_gating": False}
    assert method_options("signatures", prior_gating=False) == {"prior_gating": False}
    with pytest.raises(ValueError, match="--match"):
        method_options("signatures", match="dapc")
    with pytest.raises(ValueError, match="contradicts"):
        method_options("orb-all", point_map="reference")


def test_window_mask_equals_the_brute_force_test():
    from scenesig.localiser.pointmethod import window_mask

    rng = np.random.default_rng(3)
    xy = rng.uniform([0, 0], [640, 480], (700, 2)).astype(np.float32)
    c = rng.uniform([0, 0], [640, 480], (300, 2))
    r = rng.uniform(5, 60, (300, 2))
    win = np.column_stack([c - r, c + r])
    win[:10] = np.nan                                  # too wide: every point
    ok = rng.random(300) > 0.1                         # unsearchable: none
    x, y = xy[:, 0].astype(float), xy[:, 1].astype(float)
    with np.errstate(invalid="ignore"):
        brute = (x >= win[:, :1]) & (x <= win[:, 2:3]) & (y >= win[:, 1:2]) & (y <= win[:, 3:4])
    brute[:10] = True
    brute[~ok] = False
    assert np.array_equal(window_mask(win, ok, xy), brute)
