"""Single-experience banks: whitened HOG, synthetic conditions, the appearance rule, multi-scale
mining, the heading benchmark's one-image protocol on a sessions layout and the time-target benchmark."""
import json

import cv2
import numpy as np
import pytest

from scenesig.localiser.synthetic import synthetic_place
from scenesig.signatures import experience, hog, mining, whiten
from scenesig.signatures.augment import CONDITIONS, augment, relight, synthesise

# ---------------------------------------------------------------------------------- whitening


@pytest.mark.parametrize("radius", [0, 1, 2])
def test_folded_filter_scores_raw_hog_as_the_whitened_filter_scores_whitened_hog(radius):
    rng = np.random.default_rng(radius)
    img = synthetic_place(1, 160, 120, seed=3)[0][0]
    raw = hog.fhog(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    white, _ = whiten.whiten_level(raw, radius)
    w = rng.normal(size=(3, 4, hog.FEATURE_DIM)).astype(np.float32)
    W, b = whiten.fold_filter(w, 0.25, radius)
    assert W.shape == (3 + 2 * radius, 4 + 2 * radius, hog.FEATURE_DIM)
    for r, c in [(4, 5), (radius, radius + 2), (6, 3)]:
        s_white = float((w * white[r:r + 3, c:c + 4]).sum()) + 0.25
        s_raw = float((W * raw[r - radius:r + 3 + radius, c - radius:c + 4 + radius]).sum()) + b
        assert s_raw == pytest.approx(s_white, rel=1e-4, abs=1e-4)


def test_whitening_decorrelates_hog_of_images_it_was_not_estimated_on():
    img = cv2.cvtColor(synthetic_place(1, 320, 240, seed=5)[0][0], cv2.COLOR_BGR2GRAY)
    raw = hog.fhog(img).reshape(-1, hog.FEATURE_DIM)
    white = whiten.whiten_level(hog.fhog(img), 1)[0].reshape(-1, hog.FEATURE_DIM)

    def offdiag(x):
        c = np.corrcoef(x.T)
        return float(np.nanmean(np.abs(c - np.diag(np.diag(c)))))

    assert offdiag(white) < 0.6 * offdiag(raw)
    # the background mean whitens to zero
    mu = whiten.load_background()["mean"]
    flat = np.broadcast_to(mu, (6, 7, hog.FEATURE_DIM)).copy()
    assert np.abs(whiten.whiten_level(flat, 1)[0][1:-1, 1:-1]).max() < 1e-5


def test_partial_levels_stay_exact_in_the_shrunk_valid_box():
    img = cv2.cvtColor(synthetic_place(1, 256, 192, seed=2)[0][0], cv2.COLOR_BGR2GRAY)
    full = hog.build_pyramid(img, levels=[0])
    part = hog.build_pyramid(img, levels=[0], regions={0: (4, 12, 6, 20)})
    wf = whiten.whiten_pyramid(full, 1)
    wp = whiten.whiten_pyramid(part, 1)
    r0, r1, c0, c1 = wp.valid_region(0)
    assert (r0, r1, c0, c1) != part.valid_region(0)          # shrunk by the kernel radius
    np.testing.assert_allclose(wp.levels[0][r0:r1, c0:c1], wf.levels[0][r0:r1, c0:c1], atol=1e-5)


def test_background_file_is_packaged_and_bad_files_are_named(tmp_path):
    bg = whiten.load_background()
    assert bg["mean"].shape == (31,) and bg["gamma"].shape == (9, 9, 31, 31)
    assert int(bg["cells"]) > 100_000
    bad = tmp_path / "bg.npz"
    bad.write_bytes(b"not a zip")
    from scenesig.surveys.errors import DataError
    with pytest.raises(DataError, match="bg.npz"):
        whiten.load_background(str(bad))


def test_background_estimate_is_symmetric_and_regenerates():
    imgs = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in synthetic_place(2, 160, 120, seed=1)[0]]
    st = whiten.estimate_background(imgs, levels=[0], max_offset=2)
    g = st["gamma"]
    np.testing.assert_allclose(g[::-1, ::-1], np.transpose(g, (0, 1, 3, 2)), atol=1e-6)
    assert st["cells"] == sum(hog.fhog(im).shape[0] * hog.fhog(im).shape[1] for im in imgs)


# ---------------------------------------------------------------------------------- augmentation


def test_relit_conditions_change_light_as_the_condition_does():
    img = synthetic_place(1, 200, 150, seed=4)[0][0]
    out = {c: relight(img, c, np.random.default_rng(0)) for c in CONDITIONS}
    for c, im in out.items():
        assert im.shape == img.shape and im.dtype == np.uint8
        np.testing.assert_array_equal(im, relight(img, c, np.random.default_rng(0)))   # seeded
    assert out["night"].mean() < 0.5 * img.mean()
    assert out["fog"].std() < 0.7 * img.std()
    assert out["snow"].mean() > img.mean()
    with pytest.raises(ValueError, match="unknown condition"):
        relight(img, "sandstorm", np.random.default_rng(0))


def test_synthesise_keeps_real_images_first_and_offsets_follow_the_shifts():
    imgs = synthetic_place(2, 96, 72, seed=6)[0]
    out, offs = synthesise(imgs, [[0, 0], [5, 1]], 5, np.random.default_rng(1), 8.0, ("night",))
    assert len(out) == 7 and out[0] is imgs[0] and out[1] is imgs[1]
    assert [o[1] for o in offs] == [0, 1, 0, 1, 0, 1, 0]
    # without conditions the copies are exactly augment()'s, in turn (maps built before are unchanged)
    out2, offs2 = synthesise(imgs, [[0, 0], [0, 0]], 3, np.random.default_rng(2), 8.0)
    rng = np.random.default_rng(2)
    for k in range(3):
        ref, shift = augment(imgs[k % 2], rng, 8.0)
        np.testing.assert_array_equal(out2[2 + k], ref)
        assert offs2[2 + k][0] == pytest.approx(shift)


def test_the_rule_reads_only_the_number_of_real_appearances():
    cfg = {"mining": {"whiten": True}, "conditions": ["fog"], "colour_constancy": True}
    one = experience.settings_for(1, {"svm_C": 0.2}, cfg)
    assert one["single"] and one["mining"] == {"svm_C": 0.2, "whiten": True}
    assert one["conditions"] == ("fog",) and one["colour_constancy"]
    two = experience.settings_for(2, {"svm_C": 0.2}, cfg)
    assert not two["single"] and two["mining"] == {"svm_C": 0.2} and two["conditions"] == ()
    assert not two["colour_constancy"]
    with pytest.raises(ValueError, match="unknown single-experience"):
        experience.settings_for(1, None, {"whiten": True})


# ---------------------------------------------------------------------------------- mining


_SHAPES = {"kinds": [{"name": "square-m", "size": 0.25, "aspect": 1.0, "nx": 5, "ny": 3}]}


def test_multi_scale_and_whitened_mining_give_valid_banks():
    images, offsets = synthetic_place(6, 192, 144, seed=0, max_shift=4.0)
    big = {"kinds": [{"name": "square-l", "size": 0.45, "aspect": 1.0, "nx": 4, "ny": 2}]}
    cfg = mining.resolve_config({"shapes": big})
    base, st0 = mining.mine_place(images, offsets, config={"shapes": big})
    multi, st1 = mining.mine_place(images, offsets, config={"shapes": big, "extra_octaves": 1})
    assert st1.n_shapes == 2 * st0.n_shapes
    coarse = [c for c in multi if c.shape_index >= st0.n_shapes]
    assert coarse, "no classifier mined an octave coarser"
    for c in coarse:                                                 # an octave (4 levels) coarser
        assert c.level == mining.shape_geometry(c.box, cfg)[0] + 4
    # octave 0 is mined exactly as before (same seeds): its classifiers are unchanged
    same = [c for c in multi if c.shape_index < st0.n_shapes]
    assert [c.shape_index for c in same] == [c.shape_index for c in base]
    np.testing.assert_array_equal(same[0].weights, base[0].weights)
    white, _ = mining.mine_place(images, offsets, config={"shapes": _SHAPES, "whiten": True})
    assert len(white) > 0
    c = white[0]
    k, fh, fw = mining.shape_geometry(c.box, mining.resolve_config({"shapes": _SHAPES}))
    assert c.filter_shape == (fh + 2, fw + 2)                      # folded: one cell wider per side
    d = white.detect(images[0], top_n=1)
    assert np.isfinite(d.x[:, 0]).mean() > 0.9


# ---------------------------------------------------------------------------------- benchmarks


def test_heading_single_protocol_on_a_sessions_layout(tmp_path):
    from scenesig.benchmarks import heading as hb
    from tests.test_heading_bench import make_shifted_dataset

    root = make_shifted_dataset(tmp_path / "synth", n_places=2)
    out = tmp_path / "h.json"
    conf = tmp_path / "c.json"
    conf.write_text(json.dumps({"mining": {"shapes": _SHAPES}, "augment_copies": 5}))
    rc = hb.main([str(root), "--methods", "signatures,orb", "--single", "--map-sessions", "1",
                  "--json", str(out), "--config", str(conf), "--jobs", "1"])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["single"] is True and doc["map_sessions"] == [1]
    assert doc["pairs"] == 2 * 2                   # two places x the two other sessions, map = session 1
    sig = doc["methods"]["signatures"]
    assert all(p[1] == 0 for p in sig["per_pair"])
    assert sig["banks"] == 2                       # one bank per (place, map image)
    assert "pair's map image" in sig["training"]
    assert sig["error_rate"] <= 0.25


def test_webcam_speed_reports_the_time_target_keys(tmp_path):
    from scenesig.benchmarks import webcam_speed
    from tests.test_webcam_bench import _write_scene

    names = [f"2020{(i // 28) + 1:02d}{(i % 28) + 1:02d}_{(8 + i) % 24:02d}0000.jpg" for i in range(42)]
    _write_scene(tmp_path / "cams" / "a", names, 0, size=(160, 120))
    _write_scene(tmp_path / "cams" / "b", names[:4], 1, size=(160, 120))
    out = tmp_path / "speed.json"
    conf = tmp_path / "conf.json"
    conf.write_text(json.dumps({"signatures": {"mining": {"shapes": _SHAPES}}}))
    assert webcam_speed.main([str(tmp_path / "cams"), "--repeat", "1", "--json", str(out),
                              "--config", str(conf)]) == 0
    doc = json.loads(out.read_text())
    assert doc["train_images"] == 20 and doc["scene"] == "a"
    assert doc["mine_seconds_per_bank_20_images"] > 0 and doc["detect_hz_1024x627"] > 0
    assert doc["detect_image_size"] == [1024, 627] and doc["threads"] == 1
    assert doc["single_bank_size"] >= 0


@pytest.mark.heavy        # renders ten simulator views (~10 s on a quiet machine)
def test_simulated_webcam_folder_follows_the_webcam_protocol(tmp_path):
    from scenesig.benchmarks import simcam, webcam

    doc = simcam.render_folder(tmp_path / "cams", places=1, size=(128, 96))
    assert doc["places"] == 1
    scenes = webcam.load_scenes(tmp_path / "cams", "single", exclude=())
    (sc,) = scenes
    assert [f.stem for f in sc.train] == ["20200101_120000"]            # sunny noon trains
    conds = dict(simcam.SCHEDULE)
    assert [conds[f.stem] for f in sc.test] == ["night", "fog", "snow", "dusk", "rain"]
    assert [webcam.period_of(webcam.hour_of(f.name)) for f in sc.test] == [
        "night", "day", "day", "twilight", "day"]
    night = cv2.imread(str(sc.test[0]))
    sunny = cv2.imread(str(sc.train[0]))
    assert night.shape == (96, 128, 3) and night.mean() < sunny.mean()
