"""Webcam matching benchmark: split rules, time-of-day periods, the δ criterion and the JSON contract."""
import json

import cv2
import numpy as np
import pytest

from scenesig.benchmarks import webcam
from scenesig.localiser.synthetic import synthetic_place
from scenesig.surveys.errors import DataError


def test_hours_and_periods_from_file_names():
    assert webcam.hour_of("20130524_121500.jpg") == pytest.approx(12.25)
    assert webcam.hour_of("2012_0104_09400.jpg") == pytest.approx(9 + 40 / 60)
    assert webcam.hour_of("frame_0001.jpg") is None
    assert webcam.hour_of("20130524_251500.jpg") is None          # no hour 25
    assert [webcam.period_of(h) for h in (23.0, 4.9, 5.0, 6.9, 7.0, 18.9, 19.0, 20.9, 21.0)] == [
        "night", "night", "twilight", "twilight", "day", "day", "twilight", "twilight", "night"]
    assert webcam.period_of(None) is None


def _write_scene(folder, names, seed, size=(192, 144), night=()):
    folder.mkdir(parents=True)
    images, _ = synthetic_place(len(names), *size, seed=seed, max_shift=0.0, strength=0.6)
    for name, img in zip(names, images):
        if name in night:                          # darkened: gamma 2.2, a third of the light, noise
            f = (img.astype(np.float32) / 255.0) ** 2.2 * 0.35
            f += np.random.default_rng(seed).normal(0, 0.01, f.shape)
            img = np.clip(f * 255, 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / name), img)


def test_split_rules(tmp_path):
    names = ["20200101_010000.jpg", "20200102_110000.jpg", "20200103_130000.jpg",
             "20200104_150000.jpg", "20200105_120500.jpg", "20200106_220000.jpg"]
    _write_scene(tmp_path / "a", names, 0, size=(32, 24))
    (tmp_path / "empty").mkdir()
    multi = webcam.load_scenes(tmp_path, "multi")
    assert [s.name for s in multi] == ["a"]                       # a folder without images is no scene
    assert [f.name for f in multi[0].train] == names[0::2]
    assert [f.name for f in multi[0].test] == names[1::2]
    single = webcam.load_scenes(tmp_path, "single")
    assert [f.name for f in single[0].train] == ["20200105_120500.jpg"]   # even image nearest noon
    assert [f.name for f in webcam.load_scenes(tmp_path, "multi", exclude=["a/20200101_010000"])[0].train] \
        == ["20200102_110000.jpg", "20200104_150000.jpg", "20200106_220000.jpg"]
    with pytest.raises(DataError, match="no scene folder"):
        webcam.load_scenes(tmp_path / "empty", "multi")
    with pytest.raises(DataError, match="not a folder"):
        webcam.load_scenes(tmp_path / "missing", "multi")


def test_single_image_bank_matches_a_darkened_view_and_point_features_are_scored(tmp_path):
    root = tmp_path / "cams"
    names = ["20200101_120000.jpg", "20200101_230000.jpg", "20200102_120000.jpg", "20200103_060000.jpg"]
    _write_scene(root / "a", names, 1, night={"20200101_230000.jpg"})
    _write_scene(root / "b", names, 2)
    out = tmp_path / "res.json"
    # Two of the nine candidate-shape kinds keep the test fast; the protocol is the same.
    conf = tmp_path / "conf.json"
    conf.write_text(json.dumps({"signatures": {"mining": {"shapes": {"kinds": [
        {"name": "square-m", "size": 0.25, "aspect": 1.0, "nx": 7, "ny": 4},
        {"name": "wide", "size": 0.20, "aspect": 2.0, "nx": 4, "ny": 4}]}}}}))
    rc = webcam.main([str(root), "--train", "single", "--json", str(out), "--methods", "signatures,orb",
                      "--figure", str(tmp_path / "fig"), "--config", str(conf)])
    assert rc == 0
    s = json.loads(out.read_text())
    assert s["tolerance_px"] == 15 and s["train"] == "single" and s["scenes"] == ["a", "b"]
    assert s["test_images"] == 4
    for m in ("signatures", "orb"):
        d = s["methods"][m]
        assert set(d) >= {"correct_per_image_mean", "precision", "localisable_fraction", "by_period", "seconds"}
        assert set(d["by_period"]) == {"night", "twilight", "day"}
        assert d["by_period"]["night"]["images"] == 2 and d["by_period"]["twilight"]["images"] == 2
    sig = s["methods"]["signatures"]
    # The camera does not move: a bank mined from one image plus augmented copies finds its
    # patches at the same pixels in the darkened and the other views.
    assert sig["localisable_fraction"] == 1.0 and sig["precision"] > 0.8
    assert sig["banks"]["a"]["train_images"] == 1
    assert (tmp_path / "fig" / "single" / "webcam_a.png").is_file()
    assert (tmp_path / "fig" / "webcam_single_periods.png").is_file()


def test_correct_means_within_delta_of_the_training_position():
    tr = np.array([[10.0, 10.0], [50.0, 50.0], [0.0, 0.0], [5.0, 5.0]])
    te = np.array([[20.0, 20.0], [50.0, 65.0], [np.nan, 0.0], [5.0, 5.0]])
    assert webcam.correct_mask(tr, te, 15).tolist() == [True, False, False, True]
    assert webcam.correct_mask(np.zeros((0, 2)), np.zeros((0, 2))).shape == (0,)
    with pytest.raises(ValueError):
        webcam.correct_mask(tr, te[:2])


def test_cli_names_a_missing_folder(tmp_path, capsys):
    from scenesig.cli import main

    assert main(["bench", "webcam", str(tmp_path / "nope"), "--json", str(tmp_path / "o.json")]) == 2
    assert "nope: not a folder" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()


def test_learned_cell_signatures_are_a_method_of_their_own(tmp_path, xfeat_model, monkeypatch):
    """``signatures-hog+xfeat`` mines the same banks on stacked cells, reported beside ``signatures``."""
    monkeypatch.setenv("SCENESIG_XFEAT_MODEL", str(xfeat_model))
    root = tmp_path / "cams"
    names = ["20200101_120000.jpg", "20200101_230000.jpg", "20200102_120000.jpg"]
    _write_scene(root / "a", names, 1, night={"20200101_230000.jpg"})
    _write_scene(root / "b", names, 2)
    out = tmp_path / "res.json"
    conf = tmp_path / "conf.json"
    conf.write_text(json.dumps({"signatures": {"mining": {"shapes": {"kinds": [
        {"name": "square-m", "size": 0.25, "aspect": 1.0, "nx": 7, "ny": 4}]}}}}))
    rc = webcam.main([str(root), "--train", "single", "--json", str(out), "--methods",
                      "signatures,signatures-hog+xfeat", "--config", str(conf)])
    assert rc == 0
    s = json.loads(out.read_text())
    hog, both = s["methods"]["signatures"], s["methods"]["signatures-hog+xfeat"]
    assert hog["features"] == "hog" and "model_sha256" not in hog
    assert both["features"] == "hog+xfeat" and len(both["model_sha256"]) == 64
    assert both["config"]["mining"]["features"] == "hog+xfeat"
    assert both["localisable_fraction"] == 1.0 and both["seconds_per_test_image"] > 0
