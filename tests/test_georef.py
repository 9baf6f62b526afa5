"""Multi-run georeferencing (mapping.georef): robust PnP to the place, combination over runs."""
import numpy as np
import pytest

from scenesig.mapping.georef import combine_estimates, georeference_places, smooth_corrections, solve_relative_pose
from scenesig.mapping.places import Place
from scenesig.surveys.geometry import CAMERA_FROM_VEHICLE_AXES, Camera, invert, make_pose, rot_z, yaw_of

CAM = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
T_VC = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.2, 0.0, 1.5])


def _scene(rng, n=60):
    """Landmarks (place frame) on the street's facades and ahead, 8-60 m in front of the car."""
    x = rng.uniform(8, 60, n)
    side = rng.choice([-1.0, 1.0], n)
    y = side * rng.uniform(6, 14, n)
    z = rng.uniform(0.5, 9, n)
    return np.column_stack([x, y, z])


def _project(T_place_vehicle, P):
    T_cam_place = invert(T_place_vehicle @ T_VC)
    Pc = P @ T_cam_place[:3, :3].T + T_cam_place[:3, 3]
    uv, _ = CAM.project(Pc)
    return uv


def test_solve_relative_pose_recovers_pose_despite_outliers():
    rng = np.random.default_rng(3)
    P = _scene(rng)
    T_true = make_pose(rot_z(np.radians(2.0)), [2.0, -1.3, 0.05])   # 2 m ahead, 1.3 m right of the place
    uv = _project(T_true, P) + rng.normal(0, 1.0, (len(P), 2))
    bad = rng.choice(len(P), 12, replace=False)                      # 20 % gross outliers
    uv[bad] = rng.uniform([0, 0], [640, 480], (12, 2))
    uv[:3] = np.nan                                                  # classifiers that did not fire
    res = solve_relative_pose(uv, P, CAM, T_VC)
    assert res.ok, res.reason
    E = invert(T_true) @ res.T_place_vehicle
    assert np.linalg.norm(E[:3, 3]) < 0.1
    assert abs(np.degrees(yaw_of(E))) < 0.1
    assert res.detections == len(P) - 3
    assert not res.inlier_mask[bad].any() and res.inliers >= len(P) - 3 - 12 - 2
    assert 0 < res.position_sigma_m < 0.2


def test_solve_relative_pose_refuses_too_little_evidence():
    rng = np.random.default_rng(4)
    P = _scene(rng, 6)
    uv = _project(np.eye(4), P)
    res = solve_relative_pose(uv, P, CAM, T_VC)
    assert not res.ok and res.reason == "too_few_detections" and res.T_place_vehicle is None
    # detections unrelated to the landmarks: no consistent pose
    P = _scene(rng, 40)
    junk = rng.uniform([0, 0], [640, 480], (40, 2))
    res = solve_relative_pose(junk, P, CAM, T_VC)
    assert not res.ok
    with pytest.raises(ValueError, match="landmarks"):
        solve_relative_pose(junk, P[:10], CAM, T_VC)


def _route(n_places=12, spacing=10.0):
    """Places on a gentle curve: truth poses and distances."""
    T = []
    for i in range(n_places):
        s = spacing * i
        psi = 0.4 * np.sin(s / 60.0)
        T.append(make_pose(rot_z(psi), [s, 20.0 * (1 - np.cos(s / 60.0)), 0.2 * np.sin(s / 30.0)]))
    return np.array(T), spacing * np.arange(n_places)


def _observations(seed=0, n_runs=9, pnp_sigma=0.1, zero_mean=True, bad_runs=()):
    """Runs with INS offsets (per run: ~2 m per axis + slow drift + heading offset) past each place.

    Each run's image is displaced from the place by a known amount (another lane position, a
    different nearest frame); its "PnP" returns that true displacement plus noise.  Run 0 is the
    reference (its image defines the place frame).  With ``zero_mean`` the offsets are centred over
    the runs, so an exact combination would have no error at all.
    """
    rng = np.random.default_rng(seed)
    T_truth, dist = _route()
    off = rng.normal(0, 2.0, (n_runs, 3)) * [1, 1, 0.15]
    if zero_mean:   # the reference run 1.8 m off; the others centred so the runs' mean is zero
        off[0] = [1.2, -1.4, 0.1]
        off[1:] -= off.mean(0) * n_runs / (n_runs - 1)
    drift = rng.normal(0, 0.02, (n_runs, 3)) * [1, 1, 0.1]       # m per 10 m: slowly varying
    hoff = np.radians(rng.normal(0, 0.3, n_runs))
    if zero_mean:
        hoff -= hoff.mean()
    places, obs = [], {}
    for i, (Tt, s) in enumerate(zip(T_truth, dist)):
        recs = []
        for k in range(n_runs):
            disp = np.eye(4) if k == 0 else make_pose(rot_z(rng.normal(0, 0.03)),
                                                       [rng.uniform(-4, 4), rng.uniform(-1.5, 1.5), 0.0])
            T_true_vehicle = Tt @ disp
            ins = T_true_vehicle.copy()
            ins[:3, 3] += off[k] + drift[k] * i
            ins[:3, :3] = rot_z(hoff[k]) @ ins[:3, :3]
            if k == 0:
                T_world_place_ins = ins          # the reference INS at the place: the old map pose
                pnp = np.eye(4)
            else:
                pnp = disp @ make_pose(rot_z(rng.normal(0, np.radians(0.2))),
                                       rng.normal(0, pnp_sigma, 3) * [1, 1, 0.3])
            rec = {"run": f"run{k}", "frame": i, "T_world_vehicle_ins": ins.tolist(), "ok": True,
                   "reason": "reference" if k == 0 else "ok", "T_place_vehicle": pnp.tolist()}
            if k in bad_runs:
                if i % 2:   # a failed PnP with a garbage pose: flagged
                    rec.update(ok=False, reason="too_few_inliers",
                               T_place_vehicle=make_pose(rot_z(0.5), [7.0, -3.0, 0.0]).tolist())
                else:       # a wrong PnP that passed its own checks: inconsistent with every INS
                    rec.update(T_place_vehicle=make_pose(rot_z(0.3), [25.0, 9.0, 0.0]).tolist())
            recs.append(rec)
        places.append(Place(i, T_world_place_ins, float(s), i))
        obs[i] = recs
    return places, obs, T_truth


def _errors(poses, places, T_truth):
    pos = np.array([np.linalg.norm(poses[p.index][:2, 3] - T[:2, 3]) for p, T in zip(places, T_truth)])
    yaw = np.array([abs(np.degrees(yaw_of(invert(T) @ poses[p.index]))) for p, T in zip(places, T_truth)])
    return pos, yaw


def test_combination_removes_per_run_ins_offsets():
    places, obs, T_truth = _observations()
    ref_pos, ref_yaw = _errors({p.index: p.T_world_place for p in places}, places, T_truth)
    poses, extra = georeference_places(places, obs)
    pos, yaw = _errors(poses, places, T_truth)
    assert np.median(ref_pos) > 1.0                        # the reference INS alone is metres off
    assert np.median(pos) < 0.15 * np.median(ref_pos) and pos.max() < 0.25
    assert np.median(yaw) < 0.5 * np.median(ref_yaw)
    e = extra[0]
    assert e["method"] == "runs" and e["runs_used"] == 9 and e["runs_total"] == 9
    assert e["spread_m"] > 1.0                             # the runs' INS disagree by metres
    np.testing.assert_allclose(np.asarray(e["T_reference_ins_place"]), places[0].T_world_place)
    # roll and pitch stay the reference's; the pose is a proper rigid transform
    for p in places:
        R = poses[p.index][:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(R[2], p.T_world_place[2, :3], atol=1e-3)
    # smoothing along the route reduces the PnP noise further than per-place means
    raw, _ = georeference_places(places, obs, {"smooth_m": 0})
    raw_pos, _ = _errors(raw, places, T_truth)
    assert np.mean(pos) < np.mean(raw_pos)


def test_random_offsets_shrink_like_one_over_sqrt_n():
    # Without centring, the combination's error is the mean of the runs' offsets: ~ σ / √N
    errs_ref, errs = [], []
    for seed in range(20):
        places, obs, T_truth = _observations(seed=seed, zero_mean=False)
        errs_ref.append(_errors({p.index: p.T_world_place for p in places}, places, T_truth)[0])
        errs.append(_errors(georeference_places(places, obs)[0], places, T_truth)[0])
    # 9 runs: 1/3 in expectation (measured 0.38 over these 20 worlds)
    assert np.median(errs) < 0.5 * np.median(errs_ref)


def test_bad_pnp_runs_are_excluded():
    places, obs, T_truth = _observations(bad_runs=(3, 5))
    poses, extra = georeference_places(places, obs, {"smooth_m": 0})
    pos, _ = _errors(poses, places, T_truth)
    for p in places:
        assert extra[p.index]["runs_used"] == 7
        assert set(extra[p.index]["pnp_failed"]) == {"run3", "run5"}
    # the same as a build that never had those runs (whose offsets were centred with them: ~cm apart)
    clean = {i: [r for r in recs if r["run"] not in ("run3", "run5")] for i, recs in obs.items()}
    poses_clean, _ = georeference_places(places, clean, {"smooth_m": 0})
    for p in places:
        np.testing.assert_allclose(poses[p.index], poses_clean[p.index], atol=1e-9)
    assert np.median(pos) < 1.0
    # with the consistency check disabled, the wrong-but-"ok" PnP would drag the places by metres
    dragged, _ = georeference_places(places, obs, {"smooth_m": 0, "max_offset_m": 1e9,
                                                   "max_heading_offset_deg": 180.0, "huber_m": 1e9})
    assert np.median(_errors(dragged, places, T_truth)[0]) > 2.0


def test_places_without_usable_runs_and_reference_method():
    places, obs, T_truth = _observations()
    # place 4: only the reference run (every other PnP failed) -> correction from its neighbours
    obs[4] = [obs[4][0]] + [{**r, "ok": False, "reason": "too_few_detections", "T_place_vehicle": None}
                            for r in obs[4][1:]]
    poses, extra = georeference_places(places, obs)
    assert extra[4]["runs_used"] == 1 and len(extra[4]["pnp_failed"]) == 8
    pos, _ = _errors(poses, places, T_truth)
    assert pos[4] < 0.5
    ref, ref_extra = georeference_places(places, obs, {"method": "reference"})
    for p in places:
        np.testing.assert_array_equal(ref[p.index], p.T_world_place)
        assert ref_extra[p.index] == {"method": "reference"}
    # no observations at all: the reference poses
    none, _ = georeference_places(places, {})
    for p in places:
        np.testing.assert_allclose(none[p.index], p.T_world_place)
    with pytest.raises(ValueError, match="method"):
        georeference_places(places, obs, {"method": "gps"})
    with pytest.raises(ValueError, match="unknown georeference option"):
        georeference_places(places, obs, {"smoothing": 3})


def test_combine_estimates_is_robust_and_smoothing_fills_gaps():
    Tref = make_pose(rot_z(0.3), [5.0, 5.0, 0.0])
    rng = np.random.default_rng(1)
    E = np.stack([make_pose(rot_z(0.3 + rng.normal(0, 0.002)), [6.0, 4.0, 0.0] + rng.normal(0, 0.3, 3))
                  for _ in range(8)])
    E[0, :3, 3] += [30.0, 0.0, 0.0]                       # one wild estimate: Huber bounds its pull
    c, info = combine_estimates(Tref, E, np.ones(8, bool))
    assert np.linalg.norm(c[:2] - [1.0, -1.0]) < 0.8 and info["runs_used"] == 8
    c_none, info_none = combine_estimates(Tref, E, np.zeros(8, bool))
    assert c_none is None and info_none["runs_used"] == 0
    s = np.arange(10) * 10.0
    C = np.tile([1.0, -2.0, 0.0, 0.01], (10, 1)) + rng.normal(0, 0.2, (10, 4)) * [1, 1, 0, 0]
    C[3] = np.nan
    sm = smooth_corrections(s, C, np.ones(10), 20.0)
    assert np.isfinite(sm).all()
    assert np.abs(sm[:, :2] - [1.0, -2.0]).mean() < np.nanmean(np.abs(C[:, :2] - [1.0, -2.0]))
    filled = smooth_corrections(s, C, np.ones(10), 0.0)
    np.testing.assert_array_equal(filled[2], C[2])
    assert np.all(filled[3] == C[2]) or np.all(filled[3] == C[4])
    assert np.all(smooth_corrections(s, np.full((10, 4), np.nan), np.ones(10), 20.0) == 0)
