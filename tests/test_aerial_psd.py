"""Point-set-domain aerial matching (issue 38): the KDM diffeomorphism, the CI-stable watershed regions and
colour map of KDMM, the seed's measures on hand-computed cases, the deformed / recoloured trials, and a
small end-to-end benchmark and flight (skipped without the XFeat model)."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from scenesig.aerial import kdmm, measures as ms
from scenesig.aerial.deform import make_trial_variant
from scenesig.aerial.kdm import fit_kdm
from scenesig.aerial.trials import make_trial

MODEL = Path(__file__).resolve().parents[1] / ".." / "shared" / "models" / "xfeat" / "xfeat.onnx"


def _warp(p):
    """A smooth, invertible test warp (displacements up to ~6 px)."""
    return p + np.stack([6 * np.sin(p[:, 1] / 60.0), 5 * np.cos(p[:, 0] / 80.0)], axis=1)


# ------------------------------------------------------------------ KDM (set stage)

def test_kdm_recovers_a_known_smooth_warp_and_is_invertible():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 400, (300, 2)) * [1.0, 0.75]
    phi = fit_kdm(x, _warp(x), {"rho": 0.01})
    y = rng.uniform(20, 380, (200, 2)) * [1.0, 0.75]            # points not used in the fit
    before = np.abs(y - _warp(y)).max()
    err = np.abs(phi(y) - _warp(y)).max()
    assert before > 4.0 and err < 0.3, (before, err)
    assert phi.rms < 0.1
    assert np.abs(phi.inverse(phi(y)) - y).max() < 1e-6           # exp(-v) undoes exp(v)
    assert phi.jacobian_det(y).min() > 0                          # orientation-preserving everywhere


def test_kdm_regularisation_and_degenerate_input():
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 300, (80, 2))
    loose, stiff = fit_kdm(x, _warp(x), {"rho": 0.01}), fit_kdm(x, _warp(x), {"rho": 100.0})
    assert loose.rms < stiff.rms                                   # rho trades fit for smoothness (eq. 6)
    ident = fit_kdm(x[:2], x[:2] + 5)                              # too few points: the identity
    assert np.allclose(ident(x), x)
    with pytest.raises(ValueError, match="scales_px"):
        fit_kdm(x, x, {"scales_px": (0.0,)})
    with pytest.raises(ValueError, match="unknown"):
        fit_kdm(x, x, {"sigma": 3})


# ------------------------------------------------------------------ KDMM (domain stage)

def _blocks(seed=0):
    """Four flat blocks of different grey and colour, with noise: four obvious regions."""
    rng = np.random.default_rng(seed)
    img = np.zeros((120, 160, 3), np.float32)
    img[:60, :80] = (40, 60, 80)
    img[:60, 80:] = (200, 180, 160)
    img[60:, :80] = (120, 200, 90)
    img[60:, 80:] = (90, 90, 220)
    img += rng.normal(0, 4, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_ci_regions_follow_the_blocks_of_a_synthetic_image():
    img = _blocks()
    lab = kdmm.ci_regions(img, {"min_area": 0.05, "max_area": 0.3})
    assert lab.shape == img.shape[:2] and lab.min() >= 1
    for sl in ((slice(5, 55), slice(5, 75)), (slice(5, 55), slice(85, 155)),
               (slice(65, 115), slice(5, 75)), (slice(65, 115), slice(85, 155))):
        vals, cnt = np.unique(lab[sl], return_counts=True)
        assert cnt.max() / cnt.sum() > 0.95                       # each block's interior is one region
    interiors = [np.bincount(lab[sl].ravel()).argmax() for sl in
                 ((slice(30, 31), slice(40, 41)), (slice(30, 31), slice(120, 121)),
                  (slice(90, 91), slice(40, 41)), (slice(90, 91), slice(120, 121)))]
    assert len(set(interiors)) == 4                               # and the four blocks are different regions


def test_colour_map_explains_a_recoloured_region_but_not_a_misaligned_one():
    rng = np.random.default_rng(2)
    ref = rng.uniform(0, 255, (500, 3))
    M = np.array([[0.8, 0.1, 0.0, 20.0], [0.0, 1.2, 0.1, -10.0], [0.05, 0.0, 0.7, 30.0]])
    sensed = ref @ M[:, :3].T + M[:, 3]
    assert np.allclose(kdmm.fit_colour_map(ref, sensed), M)       # phi_c recovered exactly
    tex = cv2.resize(rng.uniform(0, 255, (30, 40, 3)).astype(np.float32), (160, 120), interpolation=cv2.INTER_CUBIC)
    tile = np.clip(tex, 0, 255)
    recoloured = np.clip(tile.reshape(-1, 3) @ M[:, :3].T + M[:, 3], 0, 255).reshape(tile.shape)
    labels = np.repeat(np.repeat(np.arange(1, 13).reshape(3, 4), 40, axis=0), 40, axis=1)
    valid = np.ones(labels.shape, bool)
    aligned = kdmm.domain_dissimilarity(recoloured, tile, valid, labels)
    shifted = kdmm.domain_dissimilarity(recoloured, np.roll(tile, 25, axis=1), valid, labels)
    assert aligned < 0.01 and shifted > 0.3
    assert kdmm.domain_dissimilarity(recoloured, tile, valid & (labels < 3), labels) == float("inf")


# ------------------------------------------------------------------ measures

def test_point_measures_on_a_hand_computed_case():
    sensed = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0], [90.0, 90.0]])
    tile = np.array([[110.0, 10.0], [121.0, 20.0], [200.0, 200.0], [131.0, 31.0]])
    to_tile = lambda xy: np.asarray(xy, float) + [100.0, 0.0]           # noqa: E731
    # truth: (110,10) (120,20) (130,30) (190,90); within 3 px of a tile keypoint: the first three -> CKN 3
    query, train = np.array([0, 1, 2, 3]), np.array([0, 3, 3, 2])      # correct: 0->0 (0 px), 2->3 (1.4 px)
    m = ms.point_measures(sensed, tile, query, train, to_tile, (150, 100), (50, 40), 0.25, 0.5)
    assert (m["KN"], m["CKN"], m["DTMPN"], m["KN_on_tile"], m["UDTMPN"]) == (4, 3, 2, 3, 1)
    assert m["RPR"] == 0.75 and m["AR"] == pytest.approx(2 / 3) and m["RR"] == pytest.approx(2 / 3)
    assert m["QR"] == 4 / 2000 and m["RT"] == 0.75


def test_decidability_auc_and_rmse_on_hand_computed_cases():
    d = ms.decidability([1.0, 3.0], [5.0, 7.0])                    # means 2 and 6, both sd sqrt(2)
    assert d["DI"] == pytest.approx(4 / np.sqrt(np.sqrt(2)))       # eq. 19 as printed: sqrt of mean sd
    assert d["d_prime"] == pytest.approx(4 / np.sqrt(2))
    assert ms.roc_auc([3, 4], [1, 2]) == 1.0
    assert ms.roc_auc([1, 2], [3, 4]) == 0.0
    assert ms.roc_auc([2, -np.inf], [2, 1]) == pytest.approx((0.5 + 1 + 0 + 0) / 4)
    rng = np.random.default_rng(3)
    tile = rng.integers(0, 255, (80, 100, 3), dtype=np.uint8)
    sensed = tile[20:60, 30:80].copy()
    ident = lambda xy: np.asarray(xy, float) + [30.0, 20.0]            # noqa: E731
    c = np.array([24.5, 19.5])
    assert ms.standardised_rmse(sensed, tile, ident, c) == pytest.approx(0.0, abs=1e-9)
    off = lambda xy: np.asarray(xy, float) + [35.0, 20.0]              # noqa: E731
    assert ms.standardised_rmse(sensed, tile, off, c) > 1.0            # unrelated noise: RMSE ~ sqrt(2)
    labels = np.repeat([[1, 2]], 40, axis=0).repeat(25, axis=1)
    assert ms.region_rmse(sensed, tile, ident, c, labels) == pytest.approx(0.0, abs=1e-9)


# ------------------------------------------------------------------ trials

def test_variant_trials_keep_the_default_protocol_and_have_exact_truth():
    from tests.test_aerial import synthetic_map

    tiles = [synthetic_map(5), synthetic_map(6)]
    for k in range(3):
        a, b = make_trial(tiles, k, 7), make_trial_variant(tiles, k, 7)
        assert np.array_equal(a.image, b.image) and np.allclose(a.centre, b.centre)
        assert a.photometric == b.photometric
    d = make_trial_variant(tiles, 1, 7, deform=True, photometric=False)
    assert 0 <= d.variant["tilt_deg"] <= 15 and 2 <= d.variant["displacement_px"] <= 10
    ys, xs = np.mgrid[5:295:37, 5:395:41]
    xy = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    p = d.to_tile(xy).astype(np.float32)
    tile = tiles[d.tile]
    samp = cv2.remap(tile, p[:, 0:1], p[:, 1:2], cv2.INTER_LINEAR)[:, 0].astype(float)
    assert np.abs(samp - d.image[ys.ravel(), xs.ravel()].astype(float)).max() <= 1.0
    assert np.allclose(d.centre, d.to_tile(np.array([[199.5, 149.5]]))[0])
    r = make_trial_variant(tiles, 1, 7, recolour_=True)
    assert r.variant["recolour"]["kind"] in ("snow", "grass", "soil") and r.variant["recolour"]["covered"] > 0.1
    again = make_trial_variant(tiles, 1, 7, recolour_=True)
    assert np.array_equal(r.image, again.image)


# ------------------------------------------------------------------ end to end (needs the model)

@pytest.fixture
def xfeat_model(monkeypatch):
    if not MODEL.is_file():
        pytest.skip(f"XFeat model not found at {MODEL} (models live beside the project in ../shared/models)")
    monkeypatch.setenv("SCENESIG_XFEAT_MODEL", str(MODEL))
    return str(MODEL)


def test_psd_stages_on_one_deformed_trial(xfeat_model):
    """Point, set and domain stages on one deformed trial of a synthetic map: each places it, KDM's
    map explains the matches at least as well as the affine, KDMM scores its own tile above another."""
    from scenesig.aerial.psd import PSDMatcher
    from tests.test_aerial import synthetic_map

    tiles = [synthetic_map(11), synthetic_map(12)]
    tr = make_trial_variant(tiles, 0, 5, deform=True)
    res = {}
    for stage in ("point", "kdm", "kdmm"):
        m = PSDMatcher({"stage": stage, "xfeat": {"model": xfeat_model}}).fit(tiles[tr.tile])
        res[stage] = m.locate(tr.image)
        assert np.linalg.norm(res[stage].centre - tr.centre) < 25, stage
    assert res["kdm"].inliers >= res["point"].inliers
    other = PSDMatcher({"stage": "kdmm", "xfeat": {"model": xfeat_model}}).fit(tiles[1 - tr.tile]).locate(tr.image)
    assert res["kdmm"].score > other.score
    with pytest.raises(ValueError, match="stage"):
        PSDMatcher({"stage": "nope"})


def test_psd_bench_end_to_end_on_deformed_trials(tmp_path, xfeat_model):
    from scenesig.benchmarks.aerial import run_benchmark
    from tests.test_aerial import _write_tiles

    root = _write_tiles(tmp_path / "tiles")
    methods = ["psd-kdmm", "xfeat-gms"]
    out = tmp_path / "out" / "aerial.json"
    doc = run_benchmark(root, methods, trials=2, seed=3, json_path=out, progress=False, deform=True,
                        measures=True, feature_cache=tmp_path / "features")
    assert json.loads(out.read_text())["protocol"]["deform"] is True
    for m in methods:
        r = doc["methods"][m]
        assert r["success_rate"] == 1.0, (m, r)
        assert r["matched_pairs"] > 0 and 0 < r["putative_match_ratio"] <= 1
        meas = r["measures"]
        assert meas["pairs"] == 2 and 0 < meas["RPR"] <= 1 and 0 <= meas["RR"] <= meas["AR"] <= 1
        assert meas["RT_s"] > 0 and meas["AUC"] is not None
    assert any((tmp_path / "features").glob("*.npz"))
    header = (out.parent / "trials.csv").read_text().splitlines()[0]
    assert "psd-kdmm_impostor_score" in header
    again = run_benchmark(root, ["psd-kdmm"], trials=2, seed=3, progress=False, deform=True,
                          feature_cache=tmp_path / "features")
    assert again["methods"]["psd-kdmm"]["median_error_px"] == doc["methods"]["psd-kdmm"]["median_error_px"]


@pytest.mark.heavy
def test_localise_flight_with_kdmm_picks_the_tiles(tmp_path, xfeat_model, capsys):
    from scenesig import cli
    from scenesig.aerial.geo import load_tiles
    from scenesig.aerial.trials import write_sequence
    from tests.test_aerial import _write_tiles

    root = _write_tiles(tmp_path / "tiles")
    write_sequence(load_tiles(root), tmp_path / "seq", n=3, seed=2)
    assert cli.main(["aerial", "localise", str(root), str(tmp_path / "seq"), "--out", str(tmp_path / "o"),
                     "--method", "psd-kdmm", "--xfeat-model", xfeat_model]) == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["method"] == "psd-kdmm" and summary["right_tile"] == 3 and summary["median_error_m"] < 1.0
    assert "score" in (tmp_path / "o" / "track.csv").read_text().splitlines()[0]
