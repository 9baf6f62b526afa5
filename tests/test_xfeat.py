"""XFeat post-processing (signatures.xfeat) on synthetic maps with known answers, its matcher, the model
location rules, and -- with ../shared/models -- the network recovering a horizontal shift."""
import os

import numpy as np
import pytest

from scenesig.signatures import xfeat
from scenesig.signatures.xfeat import DenseMaps, heatmap_from_logits, match_mnn, nms, postprocess, sample_dense


def _logits(h, w, peaks):
    """Logits whose heat map is ~0 except at ``peaks`` {(x, y): strength in logit units}."""
    lg = np.zeros((65, h, w), np.float32)
    lg[64] = 10.0                                   # "no keypoint" wins everywhere ...
    for (x, y), s in peaks.items():
        cy, cx, c = y // 8, x // 8, (y % 8) * 8 + (x % 8)
        lg[c, cy, cx] = 10.0 + s                    # ... except where a peak is placed
    return lg


def test_heatmap_pixel_shuffle_puts_each_channel_at_its_pixel():
    lg = _logits(3, 4, {(13, 9): 5.0, (0, 23): 5.0})
    heat = heatmap_from_logits(lg)
    assert heat.shape == (24, 32)
    top = np.argsort(heat.ravel())[-2:]
    assert {tuple(np.unravel_index(i, heat.shape)) for i in top} == {(9, 13), (23, 0)}
    p = np.exp(15.0) / (np.exp(15.0) + np.exp(10.0) + 63)   # softmax of the peak cell
    assert heat[9, 13] == pytest.approx(p, rel=1e-5)
    # the 64 kept channels of a cell sum to 1 minus the "no keypoint" probability
    assert heat[8:16, 8:16].sum() == pytest.approx(1 - np.exp(10.0) / (np.exp(15.0) + np.exp(10.0) + 63), rel=1e-5)


def test_nms_keeps_local_maxima_above_threshold():
    heat = np.zeros((20, 20))
    heat[5, 5], heat[6, 6], heat[15, 3], heat[2, 17] = 0.9, 0.5, 0.3, 0.04
    xy = nms(heat, threshold=0.05, kernel=5)
    assert sorted(map(tuple, xy)) == [(3, 15), (5, 5)]     # (6,6) suppressed, 0.04 below threshold
    heat[8, 8] = 0.6                                        # 3 px from (5,5): outside its 5x5 window
    assert (8, 8) in set(map(tuple, nms(heat, 0.05, 5)))


def test_sample_dense_hits_nodes_and_zero_pads():
    rng = np.random.default_rng(0)
    dense = rng.normal(size=(3, 10, 12))
    W, H = 96, 80                                    # 8x the map
    # a node (i, j) sits at image x with x * 12 / 95 - 0.5 = j
    j, i = 5, 4
    xy = np.array([[(j + 0.5) * (W - 1) / 12, (i + 0.5) * (H - 1) / 10]])
    for mode in ("nearest", "bilinear", "bicubic"):
        assert np.allclose(sample_dense(dense, xy, (W, H), mode)[0], dense[:, i, j]), mode
    const = np.ones((1, 10, 12))
    mid = np.array([[40.3, 37.7]])
    assert sample_dense(const, mid, (W, H), "bicubic")[0, 0] == pytest.approx(1.0)   # weights sum to 1
    # the corner pixel lies half a cell outside the node grid: zero padding halves a bilinear sample
    assert sample_dense(const, np.array([[0.0, 40.0]]), (W, H), "bilinear")[0, 0] == pytest.approx(0.5)


def test_postprocess_finds_the_known_peaks_ranked_by_score_times_reliability():
    h, w = 6, 8
    peaks = {(10, 12): 4.0, (37, 20): 4.0, (60, 41): 3.0, (22, 44): 0.5}
    lg = _logits(h, w, peaks)
    rel = np.full((1, h, w), 0.2, np.float32)
    rel[0, 2:4, 4:6] = 0.9                           # (37, 20) sits in a reliable region
    desc = np.zeros((64, h, w), np.float32)
    desc[0] = 3.0                                    # every cell the same direction (length 3)
    desc[1, :, 6:] = 3.0                             # ... except the right quarter
    maps = DenseMaps(desc, lg, rel, (w * 8, h * 8), scale=(2.0, 0.5), valid=(w * 8, h * 8))
    xy, score, d = postprocess(maps, top_k=10, threshold=0.05, kernel=5, interpolation="bicubic")
    found = [tuple(p) for p in (xy / [2.0, 0.5]).astype(int)]
    # the weak peak (heat ~0.08) passes 0.05; the three strong are ranked by heat x reliability
    assert found[:3] == [(37, 20), (10, 12), (60, 41)]
    assert set(found) == set(peaks)
    assert np.all(np.diff(score) <= 0) and np.all(score > 0)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    left = found.index((10, 12))
    assert np.allclose(d[left, :2], [1.0, 0.0], atol=1e-4)   # far from the boundary: the cell's direction
    xy2, _, _ = postprocess(maps, top_k=2)
    assert len(xy2) == 2 and np.allclose(xy2, xy[:2])
    # keypoints in the canvas' padding beyond the image are dropped
    cut = DenseMaps(desc, lg, rel, (w * 8, h * 8), valid=(50, h * 8))
    assert all(p[0] < 50 for p in postprocess(cut)[0])


def test_match_mnn_is_mutual_and_thresholded():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(50, 64))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    perm = rng.permutation(50)
    b = a[perm] + 0.05 * rng.normal(size=(50, 64))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    ia, ib, s = match_mnn(a, b, min_cossim=0.82)
    assert len(ia) == 50 and np.array_equal(perm[ib], ia)
    # an unrelated set: nothing passes 0.82, though mutual pairs exist without the threshold
    c = rng.normal(size=(50, 64))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    assert len(match_mnn(a, c, 0.82)[0]) == 0 and len(match_mnn(a, c, -1)[0]) > 0


def test_model_path_order_and_clear_error(tmp_path, monkeypatch):
    f = tmp_path / "x.onnx"
    f.write_bytes(b"not really")
    monkeypatch.setenv(xfeat.ENV_VAR, str(f))
    assert xfeat.model_path() == f
    assert xfeat.model_path(str(f)) == f
    monkeypatch.setenv(xfeat.ENV_VAR, str(tmp_path / "missing.onnx"))
    with pytest.raises(xfeat.ModelNotFoundError, match="missing.onnx.*SCENESIG_XFEAT_MODEL"):
        xfeat.model_path()
    monkeypatch.delenv(xfeat.ENV_VAR)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    with pytest.raises(xfeat.ModelNotFoundError, match="default location"):
        xfeat.model_path()
    assert str(tmp_path / "data" / "scenesig" / "models" / "xfeat.onnx") in str(
        pytest.raises(xfeat.ModelNotFoundError, xfeat.model_path).value)


def _texture(h, w, seed=0):
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 256, (h // 8, w // 8)).astype(np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(60):                                    # shapes with corners for the detector
        x, y = rng.integers(0, w - 30), rng.integers(0, h - 30)
        cv2.rectangle(img, (int(x), int(y)), (int(x + rng.integers(8, 30)), int(y + rng.integers(8, 30))),
                      int(rng.integers(0, 256)), -1)
    return img


def test_shifted_crop_is_recovered(xfeat_model):
    from scenesig.signatures.pointfeatures import estimate_displacement, extract

    img = _texture(384, 1100)
    cfg = {"xfeat": {"model": str(xfeat_model)}, "match": {"filter": "cossim", "mutual": True}}
    a = extract(img[:, :1024], "xfeat", n_features=4096, config=cfg)          # two tiles
    b = extract(img[:, 53:53 + 1024], "xfeat", n_features=4096, config=cfg)
    assert len(a) > 500 and a.descriptors.shape[1] == 64
    vote, m = estimate_displacement(a, b, cfg)
    assert vote.displacement == pytest.approx(-53, abs=1.0)
    assert vote.support > 0.5 * len(m) > 100


def test_tiles_stitch_like_one_pass(xfeat_model):
    """Within one tile's reach, the tiled image gives the same keypoints as that tile alone."""
    net = xfeat.XFeat({"model": str(xfeat_model)})
    img = _texture(200, 900, seed=3)
    whole = net.dense(img)
    part = net.dense(img[:, :640])
    # cells owned by the first tile (centre nearer it) equal the single pass
    own = xfeat._owner(whole.logits.shape[2], xfeat._tile_offsets(whole.canvas[0]))
    cols = np.flatnonzero(own == 0)
    assert len(cols) > 20
    assert np.allclose(whole.logits[:, :, cols], part.logits[:, :, cols], atol=1e-4)
    assert net.describe()["model_sha256"] == xfeat.model_sha256(xfeat_model)


# ------------------------------------------------------------------------- the localiser on XFeat
def _xfeat_store(tmp_path, model):
    from point_world import CAMERA, T_VC, camera_pose, planes, render, vehicle_pose

    from scenesig.mapping.pointmap import triangulate_keyframe
    from scenesig.mapping.store import MapStore, MapWriter, PlaceData
    from scenesig.surveys.geometry import make_pose, rot_z

    world = planes(seed=0)
    baselines = (-5.0, -2.5, 2.5, 5.0)
    key, _ = render(camera_pose(vehicle_pose(0.0)), world)
    images = [render(camera_pose(vehicle_pose(x)), world)[0] for x in baselines]
    poses = np.stack([vehicle_pose(x) for x in baselines])
    points, stats = triangulate_keyframe(key, images, poses, CAMERA, T_VC,
                                         {"kinds": ["xfeat"], "features": {"xfeat": {"model": str(model)}}})
    assert stats["xfeat"]["kept"] >= 100 and points["xfeat_desc"].dtype == np.float16
    empty = dict(bank_arrays={}, landmarks=np.zeros((0, 3)), covariances=np.zeros((0, 3, 3)),
                 classifier_ids=np.zeros(0, int))
    T_wp0 = make_pose(rot_z(0.3), [100.0, 50.0, 0.0])
    w = MapWriter(tmp_path / "map", CAMERA, T_VC, {"config": {"layers": ["signatures", "xfeat"]}})
    for i in (0, 1):
        w.write_place(i, PlaceData(**empty, points=points))
    w.finalise([{"index": 0, "T_world_place": T_wp0, "neighbours": [1]},
                {"index": 1, "T_world_place": T_wp0 @ vehicle_pose(10.0), "neighbours": [0]}])
    return MapStore.open(tmp_path / "map"), T_wp0, world


def test_xfeat_method_localises_a_synthetic_frame(tmp_path, xfeat_model):
    from point_world import CAMERA, T_VC, camera_pose, frame_prior, render

    from scenesig.localiser.pipeline import make_method
    from scenesig.surveys.geometry import invert

    store, T_wp0, world = _xfeat_store(tmp_path, xfeat_model)
    method = make_method("xfeat", store, CAMERA, T_VC, {"features": {"xfeat": {"model": str(xfeat_model)}}})
    cfg = method.method_config()
    assert cfg["method"] == "xfeat" and cfg["model_sha256"] == xfeat.model_sha256(xfeat_model)
    assert cfg["match"] == "mnn" and cfg["n_features"] == 4096
    T_pv, T_true, prior = frame_prior(T_wp0)
    live, _ = render(camera_pose(T_pv), world)
    m = method.solve(method.detect(live, 0, prior), 0, prior)
    assert m.constraint is not None, m.reason
    assert m.detections >= 30 and m.inliers >= 0.7 * m.detections
    err = invert(T_true) @ m.constraint.T_world_vehicle
    assert np.linalg.norm(err[:3, 3]) < 0.2


def test_xfeat_method_without_model_is_a_clear_error(tmp_path, monkeypatch):
    from point_world import CAMERA, T_VC

    from scenesig.localiser.pipeline import make_method
    from scenesig.mapping.store import MapStore, MapWriter

    w = MapWriter(tmp_path / "m", CAMERA, T_VC, {})
    w.finalise([])
    monkeypatch.setenv(xfeat.ENV_VAR, str(tmp_path / "nowhere" / "xfeat.onnx"))
    with pytest.raises(xfeat.ModelNotFoundError, match="nowhere/xfeat.onnx"):
        make_method("xfeat", MapStore.open(tmp_path / "m"), CAMERA, T_VC)


def test_using_model_names_the_model_without_touching_the_environment(tmp_path, monkeypatch):
    """using_model holds the name in a context variable: os.environ is never written, the block nests and
    restores, the 'model' setting still wins, another thread does not see it, and the HOG pyramid's helper
    threads (signatures.hog.thread_map) run in the caller's context, so learned cells find it there."""
    import threading

    from scenesig.signatures.hog import thread_map

    model, other = tmp_path / "m.onnx", tmp_path / "other.onnx"
    model.write_bytes(b"x")
    other.write_bytes(b"y")
    monkeypatch.setenv(xfeat.ENV_VAR, str(tmp_path / "users.onnx"))
    before = dict(os.environ)
    with xfeat.using_model(model):
        assert dict(os.environ) == before
        assert xfeat.model_path() == model
        assert xfeat.model_path(other) == other              # the setting wins
        with xfeat.using_model(other):
            assert xfeat.model_path() == other
        assert xfeat.model_path() == model
        assert thread_map(lambda _: xfeat.model_path(), range(4), threads=2) == [model] * 4
        seen = []
        t = threading.Thread(target=lambda: seen.append(xfeat._USING_MODEL.get()))
        t.start()
        t.join()
        assert seen == [None]                                # another thread: the lookup as it was
    assert dict(os.environ) == before
    with pytest.raises(xfeat.ModelNotFoundError, match="users.onnx"):     # back to $SCENESIG_XFEAT_MODEL
        xfeat.model_path()
    with xfeat.using_model(None):                    # nothing named: the lookup as it was
        with pytest.raises(xfeat.ModelNotFoundError, match="users.onnx"):
            xfeat.model_path()
    with xfeat.using_model(tmp_path / "missing.onnx"):
        with pytest.raises(xfeat.ModelNotFoundError, match="using_model"):   # the message says who named it
            xfeat.model_path()
