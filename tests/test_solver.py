"""The eq. 10 solver: robust LM with a motion prior, outlier gating, covariance, PnP variant."""
import dataclasses

import numpy as np
import pytest

from scenesig.localiser import _solver_kernel
from scenesig.localiser.solver import pose_exp, pose_log, solve, solve_pnp_prior
from scenesig.localiser.synthetic import synthetic_problem
from scenesig.surveys.geometry import invert, make_pose, rot_z


def inputs(p):
    return {k: v for k, v in p.items() if k not in ("T_true", "outliers")}


def pose_error(T_true, T):
    d = invert(T_true) @ T
    return np.linalg.norm(d[:3, 3]), np.degrees(np.linalg.norm(pose_log(d)[:3]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_perturbed_pose_with_20_percent_outliers(seed):
    p = synthetic_problem(50, outlier_fraction=0.2, seed=seed, pixel_sigma=0.5, landmark_sigma=0.01)
    prior_t, prior_r = pose_error(p["T_true"], p["T_place_vehicle_prior"])
    res = solve(**inputs(p))
    assert res.ok, res.reason
    t_err, r_err = pose_error(p["T_true"], res.T_place_vehicle)
    assert t_err < 0.1 and r_err < 0.05
    assert t_err < 0.3 * prior_t                       # the detections did the work, not the prior
    # Every planted outlier rejected; a 99 % gate may drop the odd good detection, not more.
    assert not np.any(res.inliers & p["outliers"])
    assert res.n_inliers >= 38 and res.n_detections == 50


def test_covariance_is_consistent():
    # NEES over repeated problems: with a correct covariance its mean is 6 (6-dof); allow 3..10.
    nees = []
    for seed in range(40):
        p = synthetic_problem(40, outlier_fraction=0.0, seed=100 + seed, pixel_sigma=1.0, landmark_sigma=0.2)
        res = solve(**inputs(p))
        assert res.ok, res.reason
        xi = pose_log(invert(res.T_place_vehicle) @ p["T_true"])
        nees.append(xi @ np.linalg.solve(res.covariance, xi))
    assert 3.0 < np.mean(nees) < 10.0


def test_landmark_covariance_is_propagated_into_image():
    # Inflating the landmarks' covariance must inflate the pose covariance (R + J P_l J^T).
    p = synthetic_problem(30, outlier_fraction=0.0, seed=3, landmark_sigma=0.05)
    small = solve(**inputs(p))
    p_big = dict(p, landmark_cov=p["landmark_cov"] * 400.0)
    big = solve(**inputs(p_big))
    assert small.ok and big.ok
    assert np.trace(big.covariance[:3, :3]) > 2 * np.trace(small.covariance[:3, :3])
    # Without a map covariance the detections are trusted more than with it.
    none = solve(**inputs(dict(p, landmark_cov=None)))
    assert np.trace(none.covariance[:3, :3]) < np.trace(small.covariance[:3, :3])


def test_whitening_matches_finite_difference_projection():
    from scenesig.localiser.solver import _Problem, default_config
    from scenesig.surveys.settings import merge_settings

    p = synthetic_problem(5, outlier_fraction=0.0, seed=4)
    cov_l = np.stack([np.diag([0.5, 0.1, 2.0])] * 5)
    prob = _Problem(p["uv"], p["R"], p["landmarks"], cov_l, p["camera"], p["T_vehicle_camera"],
                    p["T_place_vehicle_prior"], p["P_prior"], merge_settings(default_config))
    T = p["T_true"]
    W = prob.whitening(T, np.arange(5))
    T_cp = invert(T @ p["T_vehicle_camera"])

    def proj(X):
        return p["camera"].project((T_cp[:3, :3] @ X + T_cp[:3, 3])[None])[0][0]

    for i in range(5):
        G = np.stack([(proj(p["landmarks"][i] + h) - proj(p["landmarks"][i] - h)) / 2e-5
                      for h in np.eye(3) * 1e-5], axis=1)
        S = p["R"][i] + G @ cov_l[i] @ G.T
        assert np.linalg.inv(W[i].T @ W[i]) == pytest.approx(S, rel=1e-5)


def test_numpy_and_gtsam_backends_agree():
    # Two independent implementations of eq. 10 (plain least squares: they differ only in how
    # Huber whitens).  Without map covariances they are the same problem and must agree exactly.
    p = synthetic_problem(30, outlier_fraction=0.0, seed=5, landmark_sigma=0.05)
    cfg = {"huber_k": 1e6}
    exact = dict(p, landmark_cov=None)
    a = solve(**inputs(exact), config=cfg)
    b = solve(**inputs(exact), config=dict(cfg, backend="gtsam"))
    assert a.ok and b.ok
    assert pose_log(invert(a.T_place_vehicle) @ b.T_place_vehicle) == pytest.approx(np.zeros(6), abs=1e-7)
    assert b.covariance == pytest.approx(a.covariance, rel=1e-4, abs=1e-12)
    # With map covariances GTSAM marginalises the landmarks exactly, we to first order: the
    # poses agree to a small fraction of their standard deviation.
    a = solve(**inputs(p), config=cfg)
    b = solve(**inputs(p), config=dict(cfg, backend="gtsam"))
    sig = np.sqrt(np.diag(a.covariance))
    assert np.all(np.abs(pose_log(invert(a.T_place_vehicle) @ b.T_place_vehicle)) < 0.2 * sig)
    assert np.sqrt(np.diag(b.covariance)) == pytest.approx(sig, rel=0.01)


@pytest.mark.skipif(not _solver_kernel.AVAILABLE, reason="numba is not installed: the solver runs in numpy only")
@pytest.mark.parametrize("seed", [0, 7])
def test_compiled_loops_agree_with_the_numpy_code(seed):
    # The same model in compiled per-detection loops: equal to rounding, not bit for bit (sum order).
    p = synthetic_problem(45, outlier_fraction=0.2, seed=seed, pixel_sigma=0.7, landmark_sigma=0.05)
    p["landmarks"] = p["landmarks"].copy()
    T = p["T_place_vehicle_prior"]
    p["landmarks"][:3] = T[:3, 3] - 10.0 * T[:3, 0]          # three landmarks behind the vehicle
    a = solve(**inputs(p), config={"compiled": True})
    b = solve(**inputs(p), config={"compiled": False})
    assert a.ok and b.ok and a.reason == b.reason
    assert np.array_equal(a.inliers, b.inliers) and a.iterations == b.iterations and a.rounds == b.rounds
    np.testing.assert_allclose(a.T_place_vehicle, b.T_place_vehicle, rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(a.information_detections, b.information_detections, rtol=1e-8, atol=1e-8)
    assert np.all(np.isinf(a.mahalanobis_sq[:3])) and np.all(np.isinf(b.mahalanobis_sq[:3]))
    np.testing.assert_allclose(a.mahalanobis_sq, b.mahalanobis_sq, rtol=1e-8, atol=1e-10)
    assert a.cost == pytest.approx(b.cost, rel=1e-10)


def test_too_few_inliers_gives_no_constraint():
    p = synthetic_problem(12, outlier_fraction=0.0, seed=6)
    res = solve(**inputs(dict(p, uv=p["uv"][:3], R=p["R"][:3], landmarks=p["landmarks"][:3],
                              landmark_cov=p["landmark_cov"][:3])))
    assert not res.ok and res.reason == "too_few_detections" and res.constraint(np.eye(4)) is None
    # 12 detections, 10 of them garbage.
    rng = np.random.default_rng(0)
    uv = p["uv"].copy()
    uv[2:] = rng.uniform([0, 0], [640, 480], (10, 2))
    res = solve(**inputs(dict(p, uv=uv)))
    assert not res.ok and res.reason in ("too_few_inliers", "low_inlier_fraction")
    assert res.constraint(np.eye(4)) is None


def test_inconsistent_with_prior_is_rejected():
    # Exact detections, and a prior 20 sigma off laterally: the detections win, and the solver
    # reports that the answer contradicts the motion prior.
    p = synthetic_problem(40, outlier_fraction=0.0, seed=7, pixel_sigma=0.3, landmark_sigma=0.01)
    sig = np.sqrt(np.diag(p["P_prior"]))
    off = np.zeros(6)
    off[2] = 20 * sig[2]                               # 20 σ in yaw
    res = solve(**inputs(dict(p, T_place_vehicle_prior=p["T_true"] @ pose_exp(off))))
    assert not res.ok and res.reason == "inconsistent_with_prior"
    assert res.prior_chi2 > 22.46
    ok = solve(**inputs(p))
    assert ok.ok and ok.prior_chi2 < 22.46


def test_detections_only_constraint_removes_the_prior():
    # With a prior 3 σ off, the posterior is pulled towards it; the detections-only pose is not,
    # and matches a solve with an (almost) uninformative prior.
    p = synthetic_problem(40, outlier_fraction=0.0, seed=8, pixel_sigma=1.0, landmark_sigma=0.02,
                          prior_sigmas=(0.01, 0.01, 0.01, 0.3, 0.3, 0.1))
    sig = np.sqrt(np.diag(p["P_prior"]))
    T_prior = p["T_true"] @ pose_exp(np.array([0, 0, 3, 3, -3, 0]) * sig)
    res = solve(**inputs(dict(p, T_place_vehicle_prior=T_prior)), config={"prior_gate_chi2": 1e9})
    free = solve(**inputs(dict(p, T_place_vehicle_prior=res.T_place_vehicle, P_prior=p["P_prior"] * 1e8)))
    d_post = pose_error(free.T_place_vehicle, res.T_place_vehicle)[0]
    d_det = pose_error(free.T_place_vehicle, res.T_place_vehicle_detections)[0]
    assert d_det < 0.2 * d_post
    # Information from detections alone is smaller than the posterior's.
    assert np.all(np.linalg.eigvalsh(np.linalg.inv(res.covariance) - res.information_detections) > -1e-6)
    c = res.constraint(make_pose(rot_z(1.0), [5, 6, 7]))
    assert c.T_world_vehicle == pytest.approx(make_pose(rot_z(1.0), [5, 6, 7]) @ res.T_place_vehicle)


def test_distorted_camera():
    p = synthetic_problem(40, outlier_fraction=0.0, seed=9, pixel_sigma=0.3, landmark_sigma=0.01)
    cam = dataclasses.replace(p["camera"], distortion=(-0.2, 0.05, 0.001, -0.001))
    T_cp = invert(p["T_true"] @ p["T_vehicle_camera"])
    # Re-observe the noisy landmarks through the distorted camera (no pixel noise).
    uv, _ = cam.project(p["landmarks"] @ T_cp[:3, :3].T + T_cp[:3, 3])
    res = solve(**inputs(dict(p, uv=uv, camera=cam, landmark_cov=None)))
    assert res.ok, res.reason
    t, r = pose_error(p["T_true"], res.T_place_vehicle)
    assert t < 0.02 and r < 0.01


def test_pnp_variant_without_and_with_prior():
    p = synthetic_problem(80, outlier_fraction=0.3, seed=10, pixel_sigma=0.5, landmark_sigma=0.0,
                          prior_sigmas=(0.05, 0.05, 0.2, 3.0, 3.0, 1.0))
    res = solve_pnp_prior(p["uv"], p["landmarks"], p["camera"], p["T_vehicle_camera"])
    assert res.ok, res.reason
    assert res.prior_chi2 is None and res.extra["ransac_inliers"] >= 50
    t, r = pose_error(p["T_true"], res.T_place_vehicle)
    assert t < 0.1 and r < 0.05
    assert np.array_equal(res.inliers, ~p["outliers"])
    with_prior = solve_pnp_prior(p["uv"], p["landmarks"], p["camera"], p["T_vehicle_camera"],
                                 p["T_place_vehicle_prior"], p["P_prior"])
    assert with_prior.ok and pose_error(p["T_true"], with_prior.T_place_vehicle)[0] < 0.1
    # Repeatable (seeded RANSAC).
    again = solve_pnp_prior(p["uv"], p["landmarks"], p["camera"], p["T_vehicle_camera"])
    assert np.array_equal(again.T_place_vehicle, res.T_place_vehicle)


def test_pnp_fails_cleanly_on_garbage():
    rng = np.random.default_rng(0)
    p = synthetic_problem(30, outlier_fraction=0.0, seed=11)
    uv = rng.uniform([0, 0], [640, 480], (30, 2))
    res = solve_pnp_prior(uv, p["landmarks"], p["camera"], p["T_vehicle_camera"])
    assert not res.ok and res.reason in ("pnp_failed", "too_few_inliers", "low_inlier_fraction")


def test_bad_input_is_named():
    p = synthetic_problem(10, outlier_fraction=0.0, seed=12)
    with pytest.raises(ValueError, match="landmarks"):
        solve(**inputs(dict(p, landmarks=p["landmarks"][:5])))
    with pytest.raises(ValueError, match="P_prior"):
        solve(**inputs(dict(p, P_prior=-np.eye(6))))
    with pytest.raises(ValueError, match="unknown solver option"):
        solve(**inputs(p), config={"hubr_k": 1.0})
    with pytest.raises(ValueError, match="non-finite"):
        solve(**inputs(dict(p, uv=np.full((10, 2), np.nan))))


@pytest.mark.parametrize("estimator", ["poselib", "pycolmap"])
def test_robust_absolute_pose_recovers_a_known_pose_with_70_percent_outliers(estimator):
    from scenesig.localiser.absolute_pose import estimate
    from scenesig.surveys.geometry import invert

    p = synthetic_problem(200, outlier_fraction=0.7, seed=21, landmark_sigma=0.05)
    r = estimate(p["uv"], p["landmarks"], p["camera"], {"estimator": estimator})
    assert r.ok
    t, rot = pose_error(p["T_true"], invert(p["T_vehicle_camera"] @ r.T_cam_place))
    assert t < 0.2 and rot < 0.3, (t, rot)
    # the inliers are the planted correspondences: none of the outliers, nearly all of the others
    assert not (r.inliers & p["outliers"]).any()
    assert (r.inliers & ~p["outliers"]).sum() >= 0.9 * (~p["outliers"]).sum()
    # and through the whole point-feature solver, which gates on an absolute inlier count
    res = solve_pnp_prior(p["uv"], p["landmarks"], p["camera"], p["T_vehicle_camera"],
                          config={"min_inliers": 12, "min_inlier_fraction": 0.0},
                          pnp_config={"estimator": estimator})
    assert res.ok, res.reason
    assert pose_error(p["T_true"], res.T_place_vehicle)[0] < 0.2
