"""The online localiser's blocks: detector windows and eq. 5, the method interface, the localiser block
(pose graph + odometry + SE(2) snapping + place choice) and the failure rule, on a synthetic world."""
import numpy as np
import pytest
from pipeline_world import SPEED, NothingMethod, TruthMethod, make_live_run, make_map

from scenesig.localiser.detector import Detector, measurement_covariance, projection_jacobians, search_windows
from scenesig.localiser.pipeline import (
    Localiser,
    Measurement,
    WeakLocaliser,
    default_config,
    make_method,
    odometry_covariance,
)
from scenesig.localiser.replay import replay
from scenesig.localiser.solver import LocalisationConstraint, pose_exp
from scenesig.mapping.store import MapStore, MapWriter, PlaceData
from scenesig.surveys.geometry import (
    CAMERA_FROM_VEHICLE_AXES,
    Camera,
    interpolate_poses,
    invert,
    make_pose,
    rot_z,
    yaw_of,
)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline_world")
    # unbiased odometry scale (so odometry distance = true distance to ~0.1 %), a yaw and pitch drift
    run = make_live_run(root / "live", length_m=90.0, odometry_bias=(0.0, 2e-3, 4e-4, 0.0, 0.0, 0.0))
    store = make_map(root / "map", length_m=120.0)
    return run, store


def _truth_s(run, t):
    """Arc length along the road of the live run at times t (constant speed from 2 m)."""
    return 2.0 + SPEED * (np.asarray(t) - run.truth_times[0])


# ---------------------------------------------------------------------------------------- detector
def test_projection_jacobian_matches_finite_differences():
    cam = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
    T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.2, 0.0, 1.5])
    rng = np.random.default_rng(0)
    L = np.column_stack([rng.uniform(8, 40, 20), rng.uniform(-10, 10, 20), rng.uniform(-1, 6, 20)])
    T = make_pose(rot_z(0.05), [0.7, -0.3, 0.05])
    uv, Jx, Jp, front = projection_jacobians(L, T, cam, T_vc)
    assert front.all()
    eps = 1e-6
    for j in range(6):
        d = np.zeros(6)
        d[j] = eps
        uv2, _, _, _ = projection_jacobians(L, T @ pose_exp(d), cam, T_vc)
        np.testing.assert_allclose((uv2 - uv) / eps, Jx[:, :, j], rtol=1e-4, atol=1e-3)
    for j in range(3):
        L2 = L.copy()
        L2[:, j] += eps
        uv2, _, _, _ = projection_jacobians(L2, T, cam, T_vc)
        np.testing.assert_allclose((uv2 - uv) / eps, Jp[:, :, j], rtol=1e-4, atol=1e-3)


def test_search_windows_grow_with_the_prior_and_skip_invisible_landmarks():
    cam = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
    T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.2, 0.0, 1.5])
    L = np.array([[20.0, 0.0, 2.0], [20.0, 5.0, 2.0], [-10.0, 0.0, 2.0], [15.0, 60.0, 1.0]])
    Q = np.eye(2) * 4.0
    tight = np.diag([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])
    loose = np.diag([1e-4, 1e-4, 4e-3, 0.25, 1.0, 0.04])
    w1, ok1, uv = search_windows(L, None, np.eye(4), tight, cam, T_vc, Q)
    w2, ok2, _ = search_windows(L, None, np.eye(4), loose, cam, T_vc, Q)
    # behind the camera, and far off to the side of the image: not searched
    assert ok1.tolist() == [True, True, False, False]
    # tight prior: the minimum radius around the prediction
    np.testing.assert_allclose(w1[0], [uv[0, 0] - 12, uv[0, 1] - 12, uv[0, 0] + 12, uv[0, 1] + 12])
    # 1 m lateral, 3.6 deg yaw sigma, landmark 20 m ahead of the vehicle = 18.8 m ahead of the
    # camera: yaw moves it by 20 δψ across, lateral by δy, both seen at 18.8 m depth
    half_u = 0.5 * (w2[0, 2] - w2[0, 0])
    pred = 3 * np.sqrt(250.0 ** 2 * (4e-3 * 20 ** 2 + 1.0) / 18.8 ** 2 + 4.0)
    assert half_u == pytest.approx(pred, rel=0.05)
    # a window wider than half the image means "search the whole image" (NaN row)
    huge = np.diag([1e-2, 1e-2, 0.1, 4.0, 25.0, 1.0])
    w3, ok3, _ = search_windows(L, None, np.eye(4), huge, cam, T_vc, Q)
    assert ok3[0] and np.isnan(w3[0]).all()


def test_measurement_covariance_is_eq5():
    Q = np.array([[4.0, 1.0], [1.0, 9.0]])
    R = measurement_covariance(np.array([40.0, 80.0]), np.array([40.0, 40.0]), np.array([1.0, 0.5]),
                               np.array([1.0, 0.5]), Q, area_ref=1600.0)
    np.testing.assert_allclose(R[0], Q)                   # a = 1, lambda = 1, s = 1
    np.testing.assert_allclose(R[1], 2.0 / (0.5 * 0.5) * Q)  # twice the area, half as sure, half scale


def _template_map(tmp_path, image, cam, T_vc, depth=25.0, n=12, seed=0):
    """A map whose place 0 holds classifiers that are HOG templates of patches of ``image``."""
    from scenesig.signatures.bank import Bank, Classifier
    from scenesig.signatures.hog import build_pyramid

    pyr = build_pyramid(image, levels=[0, 1, 2])
    feat = pyr.levels[1]
    rng = np.random.default_rng(seed)
    fh, fw = 5, 5
    hc, wc = feat.shape[:2]
    cls, centres = [], []
    tried = 0
    while len(cls) < n and tried < 500:
        tried += 1
        r, c = int(rng.integers(0, hc - fh)), int(rng.integers(0, wc - fw))
        patch = feat[r:r + fh, c:c + fw]
        if patch.std() < 0.05:
            continue
        x, y = pyr.window_centre(1, r, c, fh, fw)
        if any(np.hypot(x - a, y - b) < 30 for a, b in centres):
            continue
        w = (patch - patch.mean()).astype(np.float32)
        s = pyr.scale(1)
        cls.append(Classifier(w, -float((w * patch).sum()) * 0.5, 1, (x - 20, y - 20, 5 * 8 / s, 5 * 8 / s), (x, y), s,
                              calibration=(20.0 / float((w * patch).sum()), 0.0)))
        centres.append((x, y))
    bank = Bank(cls, image_size=(cam.width, cam.height))
    uv = np.array(centres)
    P_c = cam.backproject(uv, np.full(len(uv), depth))
    T_pc = T_vc                              # place frame = the vehicle frame where the image was taken
    L = P_c @ T_pc[:3, :3].T + T_pc[:3, 3]
    w = MapWriter(tmp_path / "tmap", cam, T_vc, {"template": True})
    w.write_place(0, PlaceData(bank.to_arrays(), L, np.tile(np.eye(3) * 0.01, (len(L), 1, 1)),
                               np.arange(len(L), dtype=np.int64)))
    w.write_place(1, PlaceData({}, np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, np.int64)))
    w.finalise([{"index": 0, "T_world_place": np.eye(4), "neighbours": [1]},
                {"index": 1, "T_world_place": make_pose(None, [10, 0, 0]), "neighbours": [0]}])
    return MapStore.open(tmp_path / "tmap"), uv


def test_detector_finds_signatures_around_predictions_and_in_the_whole_image(tmp_path):
    from scenesig.localiser.synthetic import synthetic_place

    cam = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
    T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.2, 0.0, 1.5])
    img = synthetic_place(1, 320, 240, seed=3)[0][0]
    gray = img.mean(axis=2).astype(np.uint8)
    store, uv_true = _template_map(tmp_path, gray, cam, T_vc)
    det = Detector(store, cam, T_vc, {"Q": [[4.0, 0.0], [0.0, 4.0]]})
    P = np.diag([1e-6, 1e-6, 1e-6, 1e-3, 1e-3, 1e-3])
    good = det.detect(gray, 0, np.eye(4), P)
    assert not good.whole_image and len(good) >= 0.8 * len(uv_true)
    err = np.linalg.norm(good.uv - uv_true[good.classifier], axis=1)
    assert np.median(err) < 2.0
    # R follows eq. 5 from the firing's own area, probability and scale
    np.testing.assert_allclose(good.R[:, 0, 0], good.R[:, 1, 1])
    assert np.all(good.R[:, 0, 0] > 0) and np.all(good.R[:, 0, 1] == 0)
    # A prior 4 degrees off in yaw (~17 px) with a tight covariance: the windows are searched, and
    # every firing lies in its window -- far from the true position.
    wrong = make_pose(rot_z(np.radians(4.0)))
    win, ok, _ = search_windows(store.load_place(0).landmarks, store.load_place(0).covariances, wrong, P, cam, T_vc,
                                det.Q)
    off = det.detect(gray, 0, wrong, P)
    for k, (x, y) in zip(off.classifier, off.uv):
        x0, y0, x1, y1 = win[k]
        assert x0 - 1e-6 <= x <= x1 + 1e-6 and y0 - 1e-6 <= y <= y1 + 1e-6
    assert not np.any(np.linalg.norm(off.uv - uv_true[off.classifier], axis=1) < 5.0)
    # lost: the whole image is searched and the signatures are found again
    lost = det.detect(gray, 0, wrong, P, whole_image=True)
    assert lost.whole_image and lost.searched == len(uv_true)
    err = np.linalg.norm(lost.uv - uv_true[lost.classifier], axis=1)
    assert np.mean(err < 2.0) >= 0.8
    # a place without signatures gives an empty observation; the next place is prefetched
    det.prefetch(1)
    assert len(det.detect(gray, 1, np.eye(4), P)) == 0
    det.close()


def test_detector_rejects_images_of_the_wrong_size(tmp_path):
    from scenesig.localiser.synthetic import synthetic_place

    cam = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
    T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.2, 0.0, 1.5])
    gray = synthetic_place(1, 320, 240, seed=3)[0][0].mean(axis=2).astype(np.uint8)
    store, _ = _template_map(tmp_path, gray, cam, T_vc, n=3)
    det = Detector(store, cam, T_vc)
    with pytest.raises(ValueError, match="320x240"):
        det.detect(gray[:200], 0)
    with pytest.raises(ValueError, match="unknown detector option"):
        Detector(store, cam, T_vc, {"sigmas": 3})
    det.close()


# ------------------------------------------------------------------------------- method interface
def test_method_interface_single_and_two_stage(world):
    run, store = world

    class Incomplete(WeakLocaliser):
        pass

    with pytest.raises(NotImplementedError):
        Incomplete().measure(None, 0, None)
    with pytest.raises(NotImplementedError):
        Incomplete().detect(None, 0, None)

    class TwoStage(WeakLocaliser):
        def detect(self, image, place, prior):
            return ("obs", place)

        def solve(self, obs, place, prior):
            return Measurement(None, detections=3, reason=f"{obs[0]}@{obs[1]}")

    assert TwoStage().measure(None, 4, None).reason == "obs@4"
    c = LocalisationConstraint(np.eye(4), np.eye(6), np.eye(4), np.eye(6))
    assert Measurement.coerce(c).constraint is c
    assert Measurement.coerce(None).constraint is None
    with pytest.raises(TypeError):
        Measurement.coerce("pose")
    with pytest.raises(ValueError, match="available"):
        make_method("laser", store, run.camera, run.T_vehicle_camera)
    m = make_method("signatures", store, run.camera, run.T_vehicle_camera)
    assert m.name == "signatures"
    m.close()
    # Detector and solver options pass through the method's config and are checked by their owners.
    m = make_method("signatures", store, run.camera, run.T_vehicle_camera,
                    {"detector": {"threads": 1}, "solver": {"max_rounds": 2}})
    assert m.detector.config["threads"] == 1 and m.solver_config["max_rounds"] == 2
    m.close()
    with pytest.raises(ValueError, match="unknown detector option"):
        make_method("signatures", store, run.camera, run.T_vehicle_camera, {"detector": {"thread": 1}})
    assert Localiser(store, None, {"posegraph": {"extra_iterations": 0}}).graph is not None
    with pytest.raises(ValueError, match="unknown pose-graph option"):
        Localiser(store, None, {"posegraph": {"extra_iteration": 0}})


# ------------------------------------------------------------------------------ localiser block
def test_odometry_covariance_grows_with_distance():
    inc = make_pose(None, [0.5, 0, 0])
    c1 = odometry_covariance(inc, default_config["odometry_sigma_per_sqrt_m"], default_config["odometry_sigma_floor"])
    c2 = odometry_covariance(make_pose(None, [2.0, 0, 0]), default_config["odometry_sigma_per_sqrt_m"],
                             default_config["odometry_sigma_floor"])
    c0 = odometry_covariance(np.eye(4), default_config["odometry_sigma_per_sqrt_m"], default_config["odometry_sigma_floor"])
    assert np.all(np.diag(c2) > np.diag(c1)) and np.all(np.diag(c0) > 0)
    np.testing.assert_allclose(np.diag(c2 - c0), 4 * np.diag(c1 - c0))


def test_prior_chooses_nearest_place_by_position_and_heading(world):
    run, store = world
    truth = lambda t: run.pose_at(t, "truth")  # noqa: E731
    loc = Localiser(store, truth)
    t0 = run.truth_times[45]                   # s = 22.25 m: between places 1 (15 m) and 2 (25 m)
    loc.start(t0)
    p = loc.prior(t0)
    assert p.place == 2 and p.next_place == 3 and not p.lost
    np.testing.assert_allclose(p.T_place_vehicle, invert(store.places[2].T_world_place) @ p.T_world_vehicle)
    # P_x is the graph's marginal plus the floor: never tighter than the floor
    floor = np.diag(np.asarray(default_config["prior_floor_sigma"]) ** 2)
    assert np.linalg.eigvalsh(p.covariance - floor).min() > -1e-12
    # facing the other way, the places passed in the opposite direction are not candidates: the
    # nearest place with a compatible heading does not exist, so the nearest by position is used,
    # and "ahead" is then the previous place
    T_back = truth(t0) @ make_pose(rot_z(np.pi))
    assert loc.nearest_place(T_back) == 2
    assert loc.place_ahead(2, T_back) == 1


def test_a_standing_vehicles_frames_count_as_one_view(world):
    # The frames of a standing vehicle see the same view: their errors are one error.  They are localised
    # but add nothing to the graph, so the stated covariance does not shrink while the vehicle stands, and
    # the next frame after moving view_baseline_m enters again.
    run, store = world
    truth = lambda t: run.pose_at(t, "truth")  # noqa: E731
    t0 = run.truth_times[45]
    sigma = np.array([0.003, 0.003, 0.005, 0.3, 0.3, 0.1])
    cov = np.diag(sigma ** 2)
    still = np.eye(4)

    def fed(config):
        loc = Localiser(store, truth, config)
        loc.start(t0)
        T = truth(t0) @ make_pose(np.eye(3), [0.0, 0.2, 0.0])     # one view's error, the same on every frame
        c = Measurement(LocalisationConstraint(T, cov, T, np.linalg.inv(cov)))
        variances = []
        for i in range(1, 21):                  # 4 s standing at 5 Hz, odometry at 20 Hz
            for j in range(4):
                loc.add_odometry(t0 + 0.05 * (4 * (i - 1) + j + 1), still)
            assert loc.add_measurement(t0 + 0.2 * i, c)
            variances.append(loc.covariance(t0 + 0.2 * i)[4, 4])
        return loc, np.array(variances)

    loc, v = fed(None)
    assert np.all(v[1:] >= v[0] * (1 - 1e-6))                       # one view's information, however long
    assert len(loc.localisation_times) == 20                          # ... and every frame localised
    _, v_counted = fed({"view_baseline_m": 0.0, "view_turn_deg": 0.0})  # every frame as a new view
    assert v_counted[-1] < 0.2 * v[-1]                                 # (the test can fail: it shrinks)
    # moving on: a frame 0.3 m further enters the graph and tightens it
    t1 = t0 + 4.0
    loc.add_odometry(t1 + 0.05, make_pose(np.eye(3), [0.3, 0.0, 0.0]))
    assert not loc.same_view(t1 + 0.05)
    T = truth(t0) @ make_pose(np.eye(3), [0.3, 0.0, 0.0])
    assert loc.add_measurement(t1 + 0.05, Measurement(LocalisationConstraint(T, cov, T, np.linalg.inv(cov))))
    assert loc.covariance(t1 + 0.05)[4, 4] < v[-1]
    # turning on the spot is a new view too
    loc.add_odometry(t1 + 0.1, make_pose(rot_z(np.radians(3.0))))
    assert not loc.same_view(t1 + 0.1)


def test_estimates_are_snapped_to_the_road_plane(world):
    # Pitch drift in the odometry lifts dead reckoning off the hill road; the output stays on it.
    run, store = world
    res = replay(store, run, NothingMethod(), every=4)
    tru = interpolate_poses(run.truth_times, run.truth_poses, res.times)
    dz = np.abs(res.poses[:, 2, 3] - tru[:, 2, 3])
    assert dz.max() < 0.05
    # roll and pitch laid in the plane: the estimate's up axis is the road's
    cos_up = np.einsum("ni,ni->n", res.poses[:, :3, 2], tru[:, :3, 2])
    assert np.degrees(np.arccos(np.clip(cos_up, -1, 1))).max() < 0.3
    # ... while raw dead reckoning over the same 20 m climbs far off the road (the test can fail)
    odo = interpolate_poses(run.odometry_times, run.odometry_poses, res.times)
    dead = tru[0] @ invert(odo[0]) @ odo[40]
    assert abs(dead[2, 3] - tru[40, 2, 3]) > 0.3


def test_localises_with_a_noisy_truth_method(world):
    run, store = world
    method = TruthMethod(run)                 # 0.3 m, 0.3 deg measurement noise
    res = replay(store, run, method, every=4)
    assert method.calls == int(np.ceil(len(run) / 4))
    assert res.failures == 0 and res.localised.sum() == method.calls
    tru = interpolate_poses(run.truth_times, run.truth_poses, res.times)
    err = np.linalg.norm(res.poses[:, :2, 3] - tru[:, :2, 3], axis=1)
    ins = interpolate_poses(run.groundtruth_times, run.groundtruth_poses, res.times)
    err_ins = np.linalg.norm(ins[:, :2, 3] - tru[:, :2, 3], axis=1)
    # the graph averages the 0.3 m measurements: well below their own error, and below the INS
    assert np.median(err) < 0.15 and np.median(err) < 0.5 * np.median(err_ins)
    dyaw = np.degrees(np.abs(np.angle(np.exp(1j * (yaw_of(res.poses) - yaw_of(tru))))))
    assert np.median(dyaw) < 0.3


def test_withheld_detections_fail_and_reset_after_20m(world):
    run, store = world
    res = replay(store, run, NothingMethod(), every=4)
    s = _truth_s(run, np.concatenate([[run.truth_times[0]], res.reset_times]))
    gaps = np.diff(s)
    # 90 m driven: a reset after 20-21 m (true distance) each time, counted as failures, flagged on
    # the frame that follows it
    assert res.failures == len(res.reset_times) == res.resets.sum() == 4
    assert np.all(gaps > 20.0) and np.all(gaps < 21.0)
    for tr, i in zip(res.reset_times, np.flatnonzero(res.resets)):
        assert run.frame_times[i - 1] <= tr <= run.frame_times[i]
    assert not res.localised.any()
    assert res.distance_since_localisation.max() <= 20.0 + 0.6     # one odometry step past 20 m at most


def test_recovers_after_a_blind_stretch(world):
    run, store = world
    res = replay(store, run, TruthMethod(run, blind=[(30.0, 75.0)]), every=4)
    s_reset = _truth_s(run, np.asarray(res.reset_times))
    last_fix = _truth_s(run, run.frame_times[res.localised & (_truth_s(run, run.frame_times) < 30.0)]).max()
    # blind from ~30 m: reset 20 m later, and again 20 m after that; localised again from 75 m
    assert len(s_reset) == res.failures == 2
    assert np.all(np.diff(np.concatenate([[last_fix], s_reset])) > 20.0)
    assert np.all(np.diff(np.concatenate([[last_fix], s_reset])) < 21.0)
    after = _truth_s(run, run.frame_times) >= 75.0
    assert res.localised[after].any() and not res.resets[after].any()
