"""Scene signatures on other cell descriptors (mining's ``features``: hog | xfeat | hog+xfeat): sizes,
settings, bank storage, and -- with ../shared/models -- XFeat cells through mining and detection."""
import numpy as np
import pytest

from scenesig.signatures import hog, mining
from scenesig.signatures.bank import Bank, Classifier


def _classifier(features, fh=2, fw=3, seed=0):
    cfg = dict(hog.default_config, features=features)
    w = np.random.default_rng(seed).normal(size=(fh, fw, hog.feature_dim(cfg))).astype(np.float32)
    return Classifier(weights=w, bias=-0.5, level=1, box=(0, 0, 24, 16), nominal_xy=(12.0, 8.0),
                      nominal_scale=0.84, hog=cfg)


def test_feature_dim_of_each_descriptor_and_unknown_one_refused():
    assert [hog.feature_dim({"features": f}) for f in hog.FEATURE_KINDS] == [31, 64, 95]
    assert hog.feature_dim(None) == hog.FEATURE_DIM == 31
    with pytest.raises(ValueError, match="unknown cell features 'sift'"):
        hog.feature_dim({"features": "sift"})
    assert not hog.learned({"features": "hog"}) and hog.learned({"features": "hog+xfeat"})


def test_classifier_refuses_weights_of_another_descriptor():
    cfg = dict(hog.default_config, features="xfeat")
    with pytest.raises(ValueError, match=r"\(fh, fw, 64\) for xfeat cells"):
        Classifier(weights=np.zeros((2, 2, 31)), bias=0.0, level=1, box=(0, 0, 1, 1), nominal_xy=(0, 0),
                   nominal_scale=1.0, hog=cfg)


@pytest.mark.parametrize("features", ["xfeat", "hog+xfeat"])
def test_bank_of_learned_cells_round_trips(features):
    bank = Bank([_classifier(features, seed=s) for s in range(3)], image_size=(64, 48),
                meta={"xfeat_sha256": "ab" * 32})
    arrays = bank.to_arrays()
    assert str(arrays["hog_features"]) == features
    back = Bank.from_arrays(arrays)
    assert back.hog["features"] == features and back.meta["xfeat_sha256"] == "ab" * 32
    for a, b in zip(bank, back):
        assert np.array_equal(a.weights, b.weights) and b.hog == a.hog


def test_hog_bank_file_unchanged_and_old_banks_read_as_hog():
    bank = Bank([_classifier("hog")], image_size=(64, 48))
    arrays = bank.to_arrays()
    # a HOG bank writes exactly what it wrote before the setting existed (maps stay byte-identical)
    assert "hog_features" not in arrays and "hog_xfeat_weight" not in arrays
    back = Bank.from_arrays(arrays)
    assert back.hog["features"] == "hog" and back[0].weights.shape[2] == 31
    # a learned bank's arrays without the descriptor name are read as HOG and refused by size
    learned = Bank([_classifier("xfeat")]).to_arrays()
    del learned["hog_features"]
    with pytest.raises(ValueError, match="filter shapes need"):
        Bank.from_arrays(learned)


def test_mining_features_setting_reaches_the_pyramid_config_and_bad_combinations_fail():
    cfg = mining.resolve_config({"features": "hog+xfeat"})
    assert cfg["hog"]["features"] == "hog+xfeat"
    assert mining.resolve_config(None)["hog"]["features"] == "hog"
    with pytest.raises(ValueError, match="disagree"):
        mining.resolve_config({"features": "xfeat", "hog": {"features": "hog"}})
    with pytest.raises(ValueError, match="unknown cell features"):
        mining.resolve_config({"features": "dino"})
    with pytest.raises(ValueError, match="needs features 'hog'"):
        mining.resolve_config({"features": "hog+xfeat", "whiten": True})
    with pytest.raises(ValueError, match="texture columns"):
        mining.resolve_config({"features": "xfeat", "min_texture": 0.1})
    mining.resolve_config({"features": "hog+xfeat", "min_texture": 0.1})      # FHOG's columns are there


# ------------------------------------------------------------------------------ with the model


@pytest.fixture
def xfeat_env(xfeat_model, monkeypatch):
    monkeypatch.setenv("SCENESIG_XFEAT_MODEL", str(xfeat_model))
    return xfeat_model


def _scene(w=200, h=120, seed=0):
    rng = np.random.default_rng(seed)
    img = (rng.random((h // 4, w // 4)) * 255).astype(np.uint8)
    import cv2
    return cv2.GaussianBlur(cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC), (3, 3), 0)


def test_xfeat_cells_are_unit_length_per_8px_cell_and_stack_after_fhog(xfeat_env):
    img = _scene()
    x = hog.describe_cells(img.astype(np.float32), dict(hog.default_config, features="xfeat"))
    assert x.shape == (120 // 8, 200 // 8, 64) and x.dtype == np.float32
    assert np.allclose(np.linalg.norm(x, axis=2), 1.0, atol=1e-5)
    both = hog.describe_cells(img.astype(np.float32),
                              dict(hog.default_config, features="hog+xfeat", xfeat_weight=0.5))
    assert both.shape[2] == 95
    assert np.array_equal(both[:, :, :31], hog.fhog(img))
    assert np.allclose(both[:, :, 31:], 0.5 * x, atol=1e-6)


def test_learned_levels_are_described_whole_even_when_a_region_is_asked(xfeat_env):
    img = _scene(240, 160)
    cfg = {"features": "xfeat"}
    part = hog.build_pyramid(img, cfg, levels=[1, 2], regions={1: (2, 5, 3, 8)})
    whole = hog.build_pyramid(img, cfg, levels=[1, 2])
    assert part.regions == {}                # a network's cell depends on the whole image
    for k in (1, 2):
        assert np.array_equal(part.levels[k], whole.levels[k])
    assert not part.matches({"features": "hog"}) and part.matches(dict(hog.default_config, features="xfeat"))


def test_mining_on_xfeat_cells_fires_on_a_held_out_condition_and_guards_its_model(xfeat_env):
    from scenesig.localiser.synthetic import synthetic_place
    from scenesig.signatures.xfeat import get_xfeat

    images, offsets = synthetic_place(13, 240, 180, seed=3, max_shift=10)
    shapes_cfg = {"kinds": [{"name": "sq", "size": 0.22, "aspect": 1.0, "nx": 5, "ny": 4}]}
    bank, stats = mining.mine_place(images[:12], offsets[:12], rng=0,
                                    config={"features": "xfeat", "shapes": shapes_cfg, "search_radius_px": 16.0})
    assert stats.kept >= 3, stats.as_dict()
    assert bank.hog["features"] == "xfeat" and bank[0].weights.shape[2] == 64
    assert bank.meta["xfeat_sha256"] == get_xfeat().sha256
    held, off = images[12], offsets[12]
    nom = np.array([c.nominal_xy for c in bank])
    det = bank.detect(held)
    err = np.hypot(det.x[:, 0] - nom[:, 0] - off[0], det.y[:, 0] - nom[:, 1] - off[1])
    assert np.median(err) < 8.0, err
    # stored and read back: the same detections
    back = Bank.from_arrays(bank.to_arrays())
    d2 = back.detect(held)
    assert np.allclose(d2.x, det.x) and np.allclose(d2.score, det.score)
    # mined with one network, detected with another: refused, naming both
    back.meta["xfeat_sha256"] = "0" * 64
    with pytest.raises(ValueError, match="mined on XFeat cells of model sha256 000000000000"):
        back.detect(held)


def test_a_map_mined_on_hog_and_xfeat_cells_builds_and_localises(xfeat_env, tiny_world, tmp_path, monkeypatch):
    """``features`` through a map: the build, the stored banks, the summary and a replay."""
    from build_world import CONFIG

    from scenesig import api
    from scenesig.mapping.store import MapStore
    from scenesig.signatures.bank import Bank
    from scenesig.surveys.errors import DataError

    runs, _ = tiny_world
    config = {**CONFIG, "layers": ["signatures"], "mining": {**CONFIG["mining"], "features": "hog+xfeat"}}
    summary = api.build_map(runs, runs[0], tmp_path / "map", jobs=1, progress=False, config=config)
    assert summary["features"] == "hog+xfeat" and summary["signatures_per_place_mean"] > 0
    bank = Bank.from_arrays(MapStore.open(tmp_path / "map").load_place(0).bank_arrays)
    assert bank.hog["features"] == "hog+xfeat" and bank[0].weights.shape[2] == 95
    loc = api.localise(tmp_path / "map", runs[2].root, every=4)         # the night run
    assert loc.metrics["localised_fraction"] > 0, loc.metrics
    assert loc.method_config["features"] == "hog+xfeat"
    # without the model the replay stops before it starts, naming where it looked
    monkeypatch.delenv("SCENESIG_XFEAT_MODEL")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "nowhere"))
    with pytest.raises(DataError, match="XFeat model not found"):
        api.localise(tmp_path / "map", runs[2].root, every=4)
