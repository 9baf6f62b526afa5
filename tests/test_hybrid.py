"""Hybrid localisation: signature detections and point matches in one eq. 10 solve (localiser.hybrid)."""
import numpy as np
import pytest
from test_pointmap import keyframe_map, point_store, world  # noqa: F401  (module fixtures)

from scenesig.localiser.detector import Observation
from scenesig.localiser.hybrid import HYBRID_METHODS, default_config, fuse, signature_agreement
from scenesig.localiser.pointmethod import PointObservation
from scenesig.localiser.solver import pose_exp, pose_log, solve, solve_pnp_prior
from scenesig.localiser.synthetic import synthetic_problem
from scenesig.surveys.geometry import invert

#: a loose prior (after a few metres of dead reckoning), so that a wrong point consensus could pass it
PRIOR_SIGMAS = (0.01, 0.01, 0.03, 0.8, 0.8, 0.2)


def _frame(seed: int, n_sig: int = 40, n_pts: int = 200, sig_px: float = 3.0, pt_px: float = 1.0,
           sig_outliers: float = 0.15, pt_outliers: float = 0.3):
    """One synthetic frame: ``n_sig`` signature detections (noisier, landmarks less certain) and ``n_pts``
    point matches of the same true pose, with their outliers, and a perturbed motion prior."""
    s = synthetic_problem(n_sig, sig_outliers, seed=seed, pixel_sigma=sig_px, landmark_sigma=0.3,
                          prior_sigmas=PRIOR_SIGMAS)
    p = synthetic_problem(n_pts, pt_outliers, seed=seed + 1000, pixel_sigma=pt_px, landmark_sigma=0.05,
                          prior_sigmas=PRIOR_SIGMAS)
    # both problems share the camera, extrinsic and true pose (synthetic_problem fixes them); one prior
    assert np.allclose(s["T_true"], p["T_true"])
    sig = Observation(0, s["uv"], s["R"], s["landmarks"], s["landmark_cov"], np.arange(n_sig), np.ones(n_sig),
                      np.ones(n_sig))
    pts = PointObservation(0, p["uv"], p["R"], p["landmarks"], p["landmark_cov"], np.arange(n_pts))
    return s, sig, pts


def _error(T, T_true):
    d = pose_log(invert(T_true) @ T)
    return float(np.linalg.norm(d[3:])), float(np.linalg.norm(d[:3]))


def _signatures_alone(s):
    return solve(s["uv"], s["R"], s["landmarks"], s["T_place_vehicle_prior"], s["P_prior"], s["camera"],
                 s["T_vehicle_camera"], landmark_cov=s["landmark_cov"])


def _points_alone(s, pts):
    from scenesig.localiser.pointmethod import default_config as point_default

    return solve_pnp_prior(pts.uv, pts.xyz, s["camera"], s["T_vehicle_camera"], s["T_place_vehicle_prior"],
                           s["P_prior"], R=pts.R, points_cov=pts.cov, config=point_default["solver"])


def _fuse(s, sig, pts, **config):
    from scenesig.localiser.pointmethod import default_config as point_default

    return fuse(sig, pts, s["T_place_vehicle_prior"], s["P_prior"], s["camera"], s["T_vehicle_camera"],
                config or None, None, point_default)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_points_all_outliers_give_the_signature_answer(seed):
    """Random point matches (no consensus): the hybrid's pose is the signature method's, bit for bit."""
    s, sig, pts = _frame(seed)
    rng = np.random.default_rng(seed)
    pts.uv = np.column_stack([rng.uniform(0, 640, len(pts)), rng.uniform(0, 480, len(pts))])
    h = _fuse(s, sig, pts)
    ref = _signatures_alone(s)
    assert ref.ok and h.reason is None and h.mode == "signatures" and h.rejection == "no_consensus"
    np.testing.assert_array_equal(h.result.T_place_vehicle, ref.T_place_vehicle)
    # in the pose graph weighted by the calibrated signature noise
    k = default_config["signature_sigma_scale"] ** 2
    np.testing.assert_allclose(h.result.information_detections * k, ref.information_detections, rtol=1e-12)
    assert (h.signature_inliers, h.point_inliers) == (ref.n_inliers, 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_coherent_wrong_point_consensus_does_not_drag_the_signature_pose(seed):
    """Every point match agrees on a wrong pose 0.6 m to the side and turned by 3.4° (repeated structure, a
    wrong keyframe), within the loose prior: a strong consensus, but the signatures disagree with it (their
    projections move by ~30 px) -- the points are dropped, the signature pose stands."""
    s, sig, pts = _frame(seed, pt_outliers=0.0)
    cam, T_vc = s["camera"], s["T_vehicle_camera"]
    T_wrong = s["T_true"] @ pose_exp([0, 0, 0.06, 0.0, 0.6, 0.0])
    # the map points as seen from the wrong pose land where the live keypoints are
    T_cp = invert(T_wrong @ T_vc)
    P_c = pts.xyz @ T_cp[:3, :3].T + T_cp[:3, 3]
    pts.uv = cam.project(P_c)[0]
    h = _fuse(s, sig, pts)
    ref = _signatures_alone(s)
    assert h.mode == "signatures" and h.rejection == "disagrees_with_signatures"
    np.testing.assert_array_equal(h.result.T_place_vehicle, ref.T_place_vehicle)
    assert h.point_inliers == 0
    assert _error(h.result.T_place_vehicle, s["T_true"])[1] < 0.01 < 0.05 < _error(h.result.T_place_vehicle,
                                                                                      T_wrong)[1]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_signatures_give_the_point_answer(seed):
    s, sig, pts = _frame(seed)
    none = Observation.empty(0)
    h = _fuse(s, none, pts)
    ref = _points_alone(s, pts)
    assert ref.ok and h.reason is None and h.mode == "points"
    np.testing.assert_array_equal(h.result.T_place_vehicle, ref.T_place_vehicle)
    assert (h.signature_inliers, h.point_inliers) == (0, ref.n_inliers)
    # too few detections to solve with (fewer than the signatures' minimum): still the point answer
    few = Observation(0, sig.uv[:2], sig.R[:2], sig.landmarks[:2], sig.landmark_cov[:2], np.arange(2), np.ones(2),
                      np.ones(2))
    np.testing.assert_array_equal(_fuse(s, few, pts).result.T_place_vehicle, ref.T_place_vehicle)


def test_when_both_agree_the_hybrid_is_at_least_as_accurate_as_each():
    """Over 40 frames: the joint solve's translation and rotation errors are no worse than either
    type alone (mean), and it keeps both types' inliers."""
    errs = {"hybrid": [], "signatures": [], "points": []}
    for seed in range(40):
        s, sig, pts = _frame(seed, n_pts=60, pt_px=1.5)
        h = _fuse(s, sig, pts, point_dominant_inliers=1000)      # both weighted by their own noise
        assert h.reason is None and h.mode == "joint"
        assert h.signature_inliers >= 0.6 * len(sig) and h.point_inliers >= 0.5 * len(pts)
        errs["hybrid"].append(_error(h.result.T_place_vehicle, s["T_true"]))
        errs["signatures"].append(_error(_signatures_alone(s).T_place_vehicle, s["T_true"]))
        errs["points"].append(_error(_points_alone(s, pts).T_place_vehicle, s["T_true"]))
    mean = {k: np.mean(v, axis=0) for k, v in errs.items()}
    for other in ("signatures", "points"):
        assert mean["hybrid"][0] <= mean[other][0] * 1.001, mean
        assert mean["hybrid"][1] <= mean[other][1] * 1.001, mean


def test_a_strong_point_consensus_makes_the_signatures_the_gate():
    """With many point inliers the joint pose is (nearly) the point pose; the signatures still count."""
    s, sig, pts = _frame(3)
    h = _fuse(s, sig, pts, point_dominant_inliers=12, signature_gate_scale=10.0)
    ref = _points_alone(s, pts)
    assert h.mode == "joint" and h.dominant
    assert _error(h.result.T_place_vehicle, ref.T_place_vehicle)[0] < 0.02
    agree = signature_agreement(h.result.T_place_vehicle, sig, s["camera"], s["T_vehicle_camera"])
    assert h.signature_inliers == agree.sum() >= 0.6 * len(sig)


def test_method_names_and_command_line_options():
    from scenesig.commands.localise import METHODS
    from scenesig.localiser.pipeline import available_methods
    from scenesig.localiser.replay import method_options

    assert set(HYBRID_METHODS) <= set(available_methods()) and set(HYBRID_METHODS) <= set(METHODS)
    assert method_options("hybrid") == {}
    assert method_options("hybrid", match="dapc") == {"points": {"match": "dapc"}}
    assert method_options("hybrid-orb", prior_gating=False) == {"signatures": {"prior_gating": False},
                                                                "points": {"prior_gating": False}}
    with pytest.raises(ValueError, match="contradicts"):
        method_options("hybrid", point_map="all")
    assert method_options("hybrid-sift-all", point_map="all") == {}


def test_demo_groups_hybrid_with_the_sift_replays():
    from scenesig.demo import localise_groups

    groups = localise_groups([("r", "signatures"), ("r", "sift"), ("r", "sift-all"), ("r", "hybrid"),
                              ("r", "orb"), ("r", "hybrid-orb")])
    as_sets = [set(g) for _, g in groups]
    assert {"sift", "sift-all", "hybrid"} in as_sets and {"orb", "hybrid-orb"} in as_sets


@pytest.mark.heavy
def test_hybrid_replay_on_the_tiny_world_writes_both_inlier_counts(tmp_path_factory):
    """End to end on the tiny world's map (ORB points only): ``hybrid-orb`` on the held-out night run --
    frames.csv ends with signature_inliers, point_inliers; the metrics count both; no more failures and
    about as many localisations as the signatures alone (ORB finds nothing at night there)."""
    from build_world import tiny_map, tiny_runs

    from scenesig.localiser.outputs import FRAMES_COLUMNS, read_frames_csv
    from scenesig.localiser.replay import localise

    base = tmp_path_factory.getbasetemp()
    runs = tiny_runs(base)
    root = tiny_map(base)
    night = next(r for r in runs if r.conditions[0] == "night")
    out = tmp_path_factory.mktemp("hybrid_night")
    m = localise(root, night.root, out, method="hybrid-orb", every=1, progress=False, figure=False)
    assert FRAMES_COLUMNS[-2:] == ("signature_inliers", "point_inliers")
    header = (out / "frames.csv").read_text().splitlines()[0].split(",")
    assert header == list(FRAMES_COLUMNS)
    fr = read_frames_csv(out / "frames.csv")
    assert np.all(fr["signature_inliers"] + fr["point_inliers"] == fr["inliers"])
    sig = localise(root, night.root, out.parent / (out.name + "_sig"), method="signatures", every=1, progress=False,
                   figure=False)
    assert m["method"] == "hybrid-orb" and m["failures"] <= sig["failures"]
    # the poses of signature-only fixes are the signatures', but they enter the graph with the calibrated
    # covariance, so the priors (and a borderline frame's acceptance) can differ a little
    assert m["localisations"] >= 0.8 * sig["localisations"]
    assert sig["point_inliers_mean"] == 0 and sig["signature_inliers_mean"] > 0
    for typ in ("signature", "point"):      # zero on the frames the detector did not run
        assert m[f"{typ}_inliers_mean"] == pytest.approx(fr[f"{typ}_inliers"].sum() / m["detector_frames"])
    assert m["localisations_with_signatures"] + m["localisations_with_points"] >= m["localisations"] > 0
    assert m["cpu_seconds"] > 0 and m["cpu_ms_per_frame"] > 0
    assert m["method_config"]["point_map"] == "reference"


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_live_features_at_half_resolution_are_in_full_image_pixels(kind, point_store, world):  # noqa: F811
    """``live_scale`` 0.5 (the cheap point extraction): keypoints come back in the full image's pixels with
    twice the noise, and match the same map points at the same places."""
    from point_world import CAMERA, T_VC, camera_pose, render, vehicle_pose

    from scenesig.localiser.pipeline import make_method

    store, _ = point_store
    live, _ = render(camera_pose(vehicle_pose(3.0, 0.8, np.radians(2.0))), world)
    full = make_method(kind, store, CAMERA, T_VC).detect(live, 0, None)
    half = make_method(kind, store, CAMERA, T_VC, {"live_scale": 0.5}).detect(live, 0, None)
    assert len(half) >= 15
    common, ia, ib = np.intersect1d(full.map_index, half.map_index, return_indices=True)
    assert len(common) >= 10
    assert np.median(np.linalg.norm(full.uv[ia] - half.uv[ib], axis=1)) < 2.5     # a half-resolution pixel
    finest = 0.5 if kind == "sift" else 1.0       # σ (px) of a keypoint at the finest octave (SIFT's up-sampled)
    assert half.R[:, 0, 0].min() >= (2 * finest) ** 2 - 1e-9 > full.R[:, 0, 0].min()
    with pytest.raises(ValueError, match="live_scale"):
        make_method(kind, store, CAMERA, T_VC, {"live_scale": 2.0})
