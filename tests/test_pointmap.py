"""Point-feature baseline: triangulated keyframe maps, the store's ``points/``, DAPC, and the ORB/SIFT method."""
import numpy as np
import pytest
from point_world import CAMERA, T_VC, camera_pose, frame_prior, planes, render, vehicle_pose

from scenesig.localiser.pipeline import MotionPrior, make_method
from scenesig.localiser.pointmethod import PointLocaliser, match_to_map
from scenesig.localiser.solver import pose_exp
from scenesig.mapping.pointmap import (
    build_point_features,
    point_covariances,
    select_frames,
    triangulate_keyframe,
    triangulate_tracks,
)
from scenesig.mapping.store import MapStore, MapWriter, PlaceData, decode_place, encode_place
from scenesig.signatures.pointfeatures import PointFeatures
from scenesig.surveys.geometry import invert, make_pose, rot_z

BASELINES = (-5.0, -2.5, 2.5, 5.0)


@pytest.fixture(scope="module")
def world():
    return planes(seed=0)


@pytest.fixture(scope="module")
def keyframe_map(world):
    key, key_depth = render(camera_pose(vehicle_pose(0.0)), world)
    images = [render(camera_pose(vehicle_pose(x)), world)[0] for x in BASELINES]
    poses = np.stack([vehicle_pose(x) for x in BASELINES])
    points, stats = triangulate_keyframe(key, images, poses, CAMERA, T_VC)
    return points, stats, key_depth


def _keyframe_depths(points, kind):
    xyz = points[f"{kind}_xyz"].astype(float)
    T_cv = invert(T_VC)
    return xyz @ T_cv[2, :3] + T_cv[2, 3]


# ------------------------------------------------------------------------------------- triangulation
def test_triangulate_tracks_recovers_points_and_rejects_bad_views():
    rng = np.random.default_rng(3)
    n = 300
    # points 6-60 m ahead of the keyframe camera, spread over the image
    uv0 = np.column_stack([rng.uniform(10, 310, n), rng.uniform(10, 230, n)])
    depth = rng.uniform(6, 60, n)
    T_pc0 = T_VC                                       # keyframe camera in the place frame
    P_c = CAMERA.backproject(uv0, depth)
    X = P_c @ T_pc0[:3, :3].T + T_pc0[:3, 3]
    xs = (0.0,) + BASELINES
    T_cam_place = np.stack([invert(vehicle_pose(x) @ T_VC) for x in xs])
    uv = np.empty((n, len(xs), 2))
    for j, T in enumerate(T_cam_place):
        uv[:, j], _ = CAMERA.project(X @ T[:3, :3].T + T[:3, 3])
    sigma = 0.3
    uv_noisy = uv + rng.normal(0, sigma, uv.shape)
    uv_noisy[~CAMERA.in_image(uv.reshape(-1, 2)).reshape(n, len(xs))] = np.nan
    uv_noisy[:20, 3] += 25.0                           # a wrong match in one view: that view must be dropped
    xyz, keep, cov, reason = triangulate_tracks(uv_noisy, T_cam_place, CAMERA, {"pixel_sigma": sigma})
    # points close to the focus of expansion have no parallax and must be refused, not invented
    centre = np.linalg.norm(uv0 - [CAMERA.cx, CAMERA.cy], axis=1) < 4
    assert not keep[centre & (depth > 40)].any()
    assert keep.mean() > 0.8
    err = xyz[keep] - X[keep]
    maha = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov[keep]), err)
    assert np.mean(maha < 16.27) > 0.97               # chi2(3) 99.9 %: the covariance is honest
    rel = np.linalg.norm(err, axis=1) / depth[keep]
    assert np.median(rel) < 0.02
    k20 = keep[:20]
    assert k20.mean() > 0.8
    assert np.median(np.linalg.norm(xyz[:20][k20] - X[:20][k20], axis=1) / depth[:20][k20]) < 0.05
    # nothing kept reprojects badly in the views it kept
    assert set(np.unique(reason[~keep])) <= {"views", "behind", "depth", "reprojection", "parallax"}


def test_triangulate_tracks_needs_keyframe_and_another_view():
    uv = np.full((3, 3, 2), np.nan)
    uv[0, 0] = [100, 100]                  # keyframe only
    uv[1, 1:] = [[100, 100], [110, 100]]   # no keyframe view
    T = np.stack([invert(vehicle_pose(x) @ T_VC) for x in (0.0, 2.0, 4.0)])
    xyz, keep, cov, reason = triangulate_tracks(uv, T, CAMERA)
    assert not keep.any()
    assert list(reason) == ["views", "views", "views"]


def test_point_map_on_rendered_planes_matches_true_depth(keyframe_map):
    points, stats, key_depth = keyframe_map
    for kind, med_tol in (("orb", 0.06), ("sift", 0.04)):
        kp = points[f"{kind}_kp"]
        assert points[f"{kind}_desc"].dtype == np.uint8        # ORB always, SIFT losslessly
        assert points[f"{kind}_xyz"].dtype == np.float32 and points[f"{kind}_sigma"].dtype == np.float16
        assert len(kp) == stats[kind]["kept"] <= 500
        assert stats[kind]["kept"] >= 100
        z = _keyframe_depths(points, kind)
        true = key_depth[np.round(kp[:, 1]).astype(int), np.round(kp[:, 0]).astype(int)]
        ok = np.isfinite(true)
        assert ok.mean() > 0.95
        rel = np.abs(z[ok] - true[ok]) / true[ok]
        assert np.median(rel) < med_tol, (kind, np.median(rel))
        assert np.percentile(rel, 90) < 0.2, (kind, np.percentile(rel, 90))
        # the stored uncertainty along the ray covers the depth error (conservative, not wild)
        xyz = points[f"{kind}_xyz"].astype(float)
        along = np.linalg.norm(xyz - T_VC[:3, 3], axis=1) * np.abs(z - true) / np.maximum(z, 1e-9)
        s_along = points[f"{kind}_sigma"][:, 1].astype(float)
        assert np.median(along[ok] / s_along[ok]) < 1.0


def test_point_covariances_from_sigma():
    xyz = np.array([[10.0, 2.0, 1.5], [30.0, -5.0, 3.0]])
    sig = np.array([[0.05, 2.0], [0.1, 4.0]])
    C = point_covariances(xyz, sig, T_VC)
    r = xyz - T_VC[:3, 3]
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    for c, ri, (a, b) in zip(C, r, sig):
        assert np.isclose(ri @ c @ ri, b * b)
        w = np.linalg.eigvalsh(c)
        assert np.allclose(np.sort(w), np.sort([a * a, a * a, b * b]))


def test_select_frames_picks_baselines():
    T = np.stack([make_pose(t=[x, 0.0, 0.0]) for x in np.arange(-10, 10.5, 0.5)])
    key = int(np.flatnonzero(np.isclose(T[:, 0, 3], 0.0))[0])
    rows = select_frames(T, key, BASELINES, 0.6)
    assert [T[r, 0, 3] for r in rows] == list(BASELINES)
    short = T[np.abs(T[:, 0, 3]) < 3]
    rows = select_frames(short, int(np.flatnonzero(np.isclose(short[:, 0, 3], 0))[0]), BASELINES, 0.6)
    assert sorted(short[r, 0, 3] for r in rows) == [-2.5, 2.5]


def test_build_point_features_from_a_survey_run(tmp_path, world):
    from scenesig.mapping.places import TrainingView
    from scenesig.surveys.run import SurveyRun, read_run, write_run

    xs = np.arange(-6.0, 6.01, 0.5)
    poses = np.stack([make_pose(rot_z(0.2), [5.0, 3.0, 0.0]) @ vehicle_pose(x) for x in xs])
    t = np.arange(len(xs)) * 0.05
    run = SurveyRun(name="ref", conditions=["synthetic"], camera=CAMERA, T_vehicle_camera=T_VC,
                    rates={"camera_hz": 20.0, "odometry_hz": 20.0, "ins_hz": 20.0}, frame_times=t,
                    frame_files=[], odometry_times=t, odometry_poses=poses, groundtruth_times=t,
                    groundtruth_poses=poses, metadata={})
    images = [render(camera_pose(vehicle_pose(x)), world)[0] for x in xs]
    write_run(run, tmp_path / "ref", images=images)
    run = read_run(tmp_path / "ref")
    k = int(np.flatnonzero(xs == 0.0)[0])
    view = TrainingView(run, k, np.arange(len(xs)), invert(poses[k]) @ poses, 0.0)
    points, stats = build_point_features(view, run.camera, run.T_vehicle_camera, return_stats=True)
    assert {f"{kind}_{a}" for kind in ("orb", "sift") for a in ("kp", "desc", "xyz", "sigma")} == set(points)
    assert stats["orb"]["frames"] == 4 and stats["orb"]["kept"] >= 100
    with pytest.raises(ValueError, match="not in its own window"):
        build_point_features(TrainingView(run, k, np.arange(k), poses[:k], 0.0), run.camera, T_VC)


# ------------------------------------------------------------------------------------------ store
def test_store_round_trips_points_and_keeps_old_places_unchanged(tmp_path, keyframe_map):
    points = keyframe_map[0]
    empty = dict(bank_arrays={}, landmarks=np.zeros((0, 3)), covariances=np.zeros((0, 3, 3)),
                 classifier_ids=np.zeros(0, int))
    raw_plain = encode_place(0, PlaceData(**empty))
    assert b"points/" not in raw_plain                     # a place without points stores nothing new
    assert decode_place(raw_plain, tmp_path / "x.npz", 0).points == {}
    w = MapWriter(tmp_path / "m", CAMERA, T_VC, {})
    w.write_place(0, PlaceData(**empty, points=points))
    w.write_place(1, PlaceData(**empty))
    w.finalise([{"index": i, "T_world_place": vehicle_pose(10.0 * i), "neighbours": [1 - i]} for i in (0, 1)])
    store = MapStore.open(tmp_path / "m", verify=True)
    got = store.load_place(0).points
    assert set(got) == set(points)
    for k, v in points.items():
        assert got[k].dtype == v.dtype and np.array_equal(got[k], v)
        assert not got[k].flags.writeable
    assert store.load_place(1).points == {}
    assert store.places[0].bytes < 250_000
    with pytest.raises(ValueError, match="only numeric"):
        PlaceData(**empty, points={"orb_kp": np.array(["a"])})


# ------------------------------------------------------------------------------------------- DAPC
def _feats(values):
    d = np.zeros((len(values), 128), np.float32)
    d[:, 0] = values
    n = len(values)
    return PointFeatures("sift", np.zeros((n, 2), np.float32), np.zeros(n, np.float32), np.zeros(n, np.float32),
                         np.zeros(n, np.float32), np.zeros(n, np.int64), d)


def test_dapc_keeps_mutual_matches_below_second_minus_mean_gap():
    # map a = 0, 10, 20, 11; live b = 1, 12, 25, 100 (distances are |a - b|)
    # a1's nearest is b1 (2), but b1's nearest is a3 (1): a1 is not a mutual match.
    mapf, live = _feats([0, 10, 20, 11]), _feats([1, 12, 25, 100])
    m = match_to_map(live, mapf, "dapc")
    # mutual pairs: a0-b0 (d1 1, d2 12), a2-b2 (5, 8), a3-b1 (1, 10): mean gap (11 + 3 + 9) / 3 = 23/3
    # keep d1 < d2 - 23/3:  a0: 1 < 4.33 yes;  a2: 5 < 0.33 no;  a3: 1 < 2.33 yes
    assert sorted(zip(m.query.tolist(), m.train.tolist())) == [(0, 0), (3, 1)]
    # Lowe's ratio would keep the ambiguous a2 (5 < 0.8 * 8): DAPC is stricter here
    r = match_to_map(live, mapf, "ratio", ratio=0.8)
    assert sorted(r.query.tolist()) == [0, 2, 3]


def test_dapc_matches_an_independent_implementation():
    rng = np.random.default_rng(0)
    live = rng.normal(0, 1, (200, 128)).astype(np.float32)
    perm = rng.permutation(200)[:120]
    mapd = live[perm] + rng.normal(0, rng.uniform(0.05, 1.5, (120, 1)), (120, 128)).astype(np.float32)
    mapf = _feats(np.zeros(120))
    mapf.descriptors = mapd
    livef = _feats(np.zeros(200))
    livef.descriptors = live
    m = match_to_map(livef, mapf, "dapc")
    D = np.linalg.norm(mapd[:, None, :].astype(float) - live[None].astype(float), axis=2)
    nn = D.argmin(axis=1)
    srt = np.sort(D, axis=1)
    d1, d2 = srt[:, 0], srt[:, 1]
    mutual = D.argmin(axis=0)[nn] == np.arange(120)
    gap = np.mean((d2 - d1)[mutual])
    expect = np.flatnonzero(mutual & (d1 < d2 - gap))
    assert np.array_equal(np.sort(m.query), expect)
    assert np.array_equal(m.train[np.argsort(m.query)], nn[expect])
    assert 0 < len(expect) < mutual.sum()          # the test is not vacuous


# --------------------------------------------------------------------------------------- the method
@pytest.fixture(scope="module")
def point_store(tmp_path_factory, keyframe_map):
    points = keyframe_map[0]
    root = tmp_path_factory.mktemp("pointmap") / "map"
    T_wp0 = make_pose(rot_z(0.3), [100.0, 50.0, 0.0])
    empty = dict(bank_arrays={}, landmarks=np.zeros((0, 3)), covariances=np.zeros((0, 3, 3)),
                 classifier_ids=np.zeros(0, int))
    w = MapWriter(root, CAMERA, T_VC, {})
    for i in (0, 1):
        w.write_place(i, PlaceData(**empty, points=points))
    w.finalise([{"index": 0, "T_world_place": T_wp0, "neighbours": [1]},
                {"index": 1, "T_world_place": T_wp0 @ vehicle_pose(10.0), "neighbours": [0]}])
    return MapStore.open(root), T_wp0


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_point_method_localises_a_synthetic_frame(point_store, world, kind):
    store, T_wp0 = point_store
    T_pv, T_true, prior = frame_prior(T_wp0)
    live, _ = render(camera_pose(T_pv), world)
    method = make_method(kind, store, CAMERA, T_VC)
    assert isinstance(method, PointLocaliser) and method.name == kind
    m = method.solve(method.detect(live, 0, prior), 0, prior)
    assert m.constraint is not None, m.reason
    assert m.detections >= 30 and m.inliers >= 0.8 * m.detections
    err = invert(T_true) @ m.constraint.T_world_vehicle
    assert np.linalg.norm(err[:3, 3]) < 0.15
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 0.3
    # a view of another street (a differently textured world) gives no constraint
    other, _ = render(camera_pose(T_pv), planes(seed=7))
    m2 = method.solve(method.detect(other, 0, prior), 0, prior)
    assert m2.constraint is None and m2.reason is not None


def test_point_method_refuses_a_map_without_points(tmp_path):
    empty = dict(bank_arrays={}, landmarks=np.zeros((0, 3)), covariances=np.zeros((0, 3, 3)),
                 classifier_ids=np.zeros(0, int))
    w = MapWriter(tmp_path / "m", CAMERA, T_VC, {})
    for i in (0, 1):
        w.write_place(i, PlaceData(**empty))
    w.finalise([{"index": i, "T_world_place": vehicle_pose(10.0 * i), "neighbours": [1 - i]} for i in (0, 1)])
    with pytest.raises(ValueError, match="no ORB point features"):
        make_method("orb", MapStore.open(tmp_path / "m"), CAMERA, T_VC)


def test_add_to_map_gives_an_existing_map_point_features(tmp_path, world):
    from scenesig.mapping.places import define_places
    from scenesig.mapping.pointmap import add_to_map
    from scenesig.surveys.run import SurveyRun, read_run, write_run

    xs = np.arange(-6.0, 16.01, 1.0)
    poses = np.stack([vehicle_pose(x) for x in xs])
    t = np.arange(len(xs)) * 0.1
    run = SurveyRun(name="ref", conditions=["synthetic"], camera=CAMERA, T_vehicle_camera=T_VC,
                    rates={"camera_hz": 10.0, "odometry_hz": 10.0, "ins_hz": 10.0}, frame_times=t, frame_files=[],
                    odometry_times=t, odometry_poses=poses, groundtruth_times=t, groundtruth_poses=poses, metadata={})
    write_run(run, tmp_path / "ref", images=[render(camera_pose(vehicle_pose(x)), world)[0] for x in xs])
    run = read_run(tmp_path / "ref")
    places = define_places(run)
    assert len(places) == 2
    w = MapWriter(tmp_path / "m", CAMERA, T_VC, {"reference": "ref", "config": {"places": {}}})
    bank = {"weights": np.arange(12, dtype=np.float32)}
    for p in places:
        w.write_place(p.index, PlaceData(bank, np.ones((1, 3)), np.eye(3)[None], np.zeros(1, int),
                                         meta={"reference_frame": p.reference_frame}))
    w.finalise([p.to_dict() for p in places])
    before = MapStore.open(tmp_path / "m")
    summary = add_to_map(tmp_path / "m", run, progress=False)
    assert summary["places"] == 2 and summary["orb_kept_mean"] >= 50
    store = MapStore.open(tmp_path / "m", verify=True)
    for p in places:
        d = store.load_place(p.index)
        assert d.points["orb_xyz"].shape[0] >= 50 and d.points["sift_xyz"].shape[0] > 0
        assert np.array_equal(d.bank_arrays["weights"], bank["weights"]) and d.meta["reference_frame"] == p.reference_frame
        assert store.places[p.index].sha256 != before.places[p.index].sha256
        # points are in the place frame: the keyframe camera sees them in front, where the keypoints are
        xyz = d.points["orb_xyz"].astype(float)
        T_cv = invert(T_VC)
        uv, z = CAMERA.project(xyz @ T_cv[:3, :3].T + T_cv[:3, 3])
        assert np.all(z > 0) and np.median(np.linalg.norm(uv - d.points["orb_kp"], axis=1)) < 1.0
    assert add_to_map(tmp_path / "m", run, progress=False)["places"] == 0      # nothing left to add
    other = SurveyRun(**{**run.__dict__, "name": "other"})
    with pytest.raises(ValueError, match="reference run 'ref'"):
        add_to_map(tmp_path / "m", other, progress=False)


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_all_point_map_retrieves_the_best_keyframe_and_localises(tmp_path, world, keyframe_map, kind):
    """``orb-all`` / ``sift-all``: keyframes from two runs (the second 12 m further on, in its own
    frame, moved into the place frame); a live image near the second is matched to it."""
    from scenesig.mapping.pointmap import combine_keyframe_maps

    T_p1 = vehicle_pose(12.0, 0.5, np.radians(3.0))       # second keyframe in the place frame
    key1 = render(camera_pose(T_p1), world)[0]
    imgs = [render(camera_pose(T_p1 @ vehicle_pose(x)), world)[0] for x in BASELINES]
    pts1, _ = triangulate_keyframe(key1, imgs, np.stack([vehicle_pose(x) for x in BASELINES]), CAMERA, T_VC)
    ref = keyframe_map[0]
    points = {**ref, **combine_keyframe_maps([ref, pts1], [np.eye(4), T_p1])}
    w = MapWriter(tmp_path / "m", CAMERA, T_VC, {})
    empty = dict(bank_arrays={}, landmarks=np.zeros((0, 3)), covariances=np.zeros((0, 3, 3)),
                 classifier_ids=np.zeros(0, int))
    w.write_place(0, PlaceData(**empty, points=points))
    w.finalise([{"index": 0, "T_world_place": np.eye(4), "neighbours": []}])
    store = MapStore.open(tmp_path / "m")
    method = make_method(f"{kind}-all", store, CAMERA, T_VC)
    assert method.name == f"{kind}-all" and method.method_config()["point_map"] == "all"
    T_pv = vehicle_pose(14.0, 0.3, np.radians(1.0))
    live, _ = render(camera_pose(T_pv), world)
    P = np.diag([0.01, 0.01, 0.03, 1.0, 1.0, 0.3]) ** 2
    prior = MotionPrior(0.0, T_pv @ pose_exp([0.005, -0.005, 0.02, 0.5, -0.4, 0.1]), P, 0, np.eye(4), None,
                        False, 0.0)
    obs = method.detect(live, 0, prior)
    assert obs.extra["keyframe"] == 1 and obs.extra["gated"]
    m = method.solve(obs, 0, prior)
    assert m.constraint is not None, m.reason
    err = invert(T_pv) @ m.constraint.T_world_vehicle
    assert np.linalg.norm(err[:3, 3]) < 0.2
