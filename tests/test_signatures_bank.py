"""One-pass bank detection against brute-force correlation; storage round trip."""
import numpy as np
import pytest

from scenesig.signatures import hog
from scenesig.signatures.bank import Bank, Classifier, score_maps_bruteforce
from scenesig.signatures.detection import _score_all


def _bank(rng, specs):
    return Bank([Classifier(rng.normal(size=(fh, fw, 31)).astype(np.float32), float(b), lv,
                            (0, 0, 8 * fw, 8 * fh), (50.0, 40.0), 1.0, calibration=(0.5, -1.0),
                            kind="k", quality=float(i), spread=(1.0, 2.0), shape_index=i)
                 for i, (fh, fw, lv, b) in enumerate(specs)])


SPECS = [(3, 4, 0, 0.3), (5, 4, 0, -0.2), (2, 2, 1, 0.0), (4, 3, 1, 1.0), (3, 4, 1, 0.5),
         (2, 6, 2, 0.1)]


@pytest.fixture
def pyramid():
    import cv2
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160), dtype=np.uint8), (3, 3), 1)
    return hog.build_pyramid(img, levels=[0, 1, 2, 3])


def test_one_pass_scores_equal_bruteforce(pyramid):
    bank = _bank(np.random.default_rng(0), SPECS)
    maps = _score_all(bank.classifiers, pyramid, [[0, 1, 2, 3]] * len(bank), None)
    for c, entries in zip(bank, maps):
        assert len(entries) >= 3
        for k, r0, c0, m in entries:
            ref = score_maps_bruteforce(c, pyramid.levels[k])
            assert (r0, c0) == (0, 0) and m.shape == ref.shape
            np.testing.assert_allclose(m, ref, atol=1e-4)


def test_windows_restrict_and_preserve_scores(pyramid):
    bank = _bank(np.random.default_rng(0), SPECS)
    win = np.array([[40, 30, 90, 70]] * len(bank), float)
    win[2] = np.nan                                          # classifier 2 unrestricted
    maps = _score_all(bank.classifiers, pyramid, [[c.level] for c in bank], win)
    for i, (c, entries) in enumerate(zip(bank, maps)):
        k, r0, c0, m = entries[0]
        ref = score_maps_bruteforce(c, pyramid.levels[k])
        np.testing.assert_allclose(m, ref[r0:r0 + m.shape[0], c0:c0 + m.shape[1]], atol=1e-4)
        if i != 2:
            assert m.size < ref.size
    det = bank.detect(pyramid, windows=win, config={"refine": False})
    for i in range(len(bank)):
        if i == 2:
            continue
        assert 40 <= det.x[i, 0] <= 90 and 30 <= det.y[i, 0] <= 70


def test_best_detection_is_the_global_maximum(pyramid):
    bank = _bank(np.random.default_rng(5), SPECS)
    det = bank.detect(pyramid, config={"refine": False, "scale_search": 1})
    for i, c in enumerate(bank):
        best = -np.inf
        for k in range(max(0, c.level - 1), c.level + 2):
            if k in pyramid.levels:
                best = max(best, score_maps_bruteforce(c, pyramid.levels[k]).max())
        assert abs(det.score[i, 0] - best) < 1e-4
        assert abs(det.prob[i, 0] - c.probability(det.score[i, 0])) < 1e-12


def test_top_n_with_nms(pyramid):
    bank = _bank(np.random.default_rng(6), SPECS)
    det = bank.detect(pyramid, top_n=3, config={"nms_iou": 0.3})
    assert det.x.shape == (len(bank), 3)
    for i in range(len(bank)):
        s = det.score[i]
        assert np.all(np.diff(s[np.isfinite(s)]) <= 1e-9)           # best first
        boxes = np.stack([det.boxes(r)[i] for r in range(3)])
        for a in range(3):
            for b in range(a + 1, 3):
                if np.all(np.isfinite(boxes[[a, b]])):
                    ix = max(0, min(boxes[a, 2], boxes[b, 2]) - max(boxes[a, 0], boxes[b, 0]))
                    iy = max(0, min(boxes[a, 3], boxes[b, 3]) - max(boxes[a, 1], boxes[b, 1]))
                    inter = ix * iy
                    ua = ((boxes[a, 2] - boxes[a, 0]) * (boxes[a, 3] - boxes[a, 1])
                          + (boxes[b, 2] - boxes[b, 0]) * (boxes[b, 3] - boxes[b, 1]) - inter)
                    assert inter / ua <= 0.3 + 1e-9


def test_subcell_refinement_finds_a_shifted_pattern():
    import cv2
    rng = np.random.default_rng(7)
    base = cv2.GaussianBlur(rng.integers(0, 255, (160, 200), dtype=np.uint8), (5, 5), 2)
    pyr0 = hog.build_pyramid(base, levels=[0])
    w = pyr0.levels[0][5:11, 6:14].copy()                   # template at cells (5, 6)
    w = (w - w.mean()).astype(np.float32)
    bank = Bank([Classifier(w, 0.0, 0, (48, 40, 64, 48), (80.0, 64.0), 1.0)])
    for shift in (0, 3, 5):
        img = np.roll(base, shift, axis=1)
        det = bank.detect(hog.build_pyramid(img, levels=[0]), config={"scale_search": 0})
        x0, _ = pyr0.window_centre(0, 5, 6, 6, 8)
        assert abs(det.x[0, 0] - (x0 + shift)) < 3.0


def test_arrays_round_trip_and_validation():
    bank = _bank(np.random.default_rng(0), SPECS)
    bank.image_size = (160, 120)
    bank.meta = {"place": 7}
    d = bank.to_arrays()
    assert all(isinstance(v, np.ndarray) for v in d.values())
    back = Bank.from_arrays(d)
    assert len(back) == len(bank) and back.image_size == (160, 120) and back.meta["place"] == 7
    for a, b in zip(bank, back):
        np.testing.assert_array_equal(a.weights, b.weights)
        assert (a.bias, a.level, a.kind, a.shape_index, a.spread) == \
               (b.bias, b.level, b.kind, b.shape_index, b.spread)
        assert a.calibration == b.calibration and a.nominal_xy == b.nominal_xy
    # float16 only where exact.
    assert d["weights"].dtype == np.float32
    assert d["box"].dtype == np.float16
    np.savez(__import__("io").BytesIO(), **d)                 # storable without pickles
    bad = dict(d)
    bad["weights"] = d["weights"][:-1]
    with pytest.raises(ValueError, match="weights"):
        Bank.from_arrays(bad)
    bad = dict(d)
    del bad["bias"]
    with pytest.raises(ValueError, match="bias"):
        Bank.from_arrays(bad)


def test_bank_selection_and_errors(pyramid):
    bank = _bank(np.random.default_rng(0), SPECS)
    assert len(bank.best(2)) == 2 and [c.quality for c in bank.best(2)] == [4.0, 5.0]
    assert len(bank[1:3]) == 2
    with pytest.raises(ValueError):
        bank.detect(pyramid, windows=np.zeros((2, 4)))
    with pytest.raises(ValueError):
        bank.detect(pyramid, top_n=0)
    other = hog.build_pyramid(np.zeros((64, 64), np.uint8), {"cell": 4}, levels=[0])
    with pytest.raises(ValueError, match="HOG parameters"):
        bank.detect(other)
    with pytest.raises(ValueError):
        Classifier(np.zeros((2, 2, 30), np.float32), 0.0, 0, (0, 0, 1, 1), (0, 0), 1.0)


def test_empty_bank_stores_and_detects():
    b = Bank.from_arrays(Bank([]).to_arrays())
    assert len(b) == 0
    assert b.detect(np.zeros((64, 64), np.uint8)).x.shape == (0, 1)


def test_windowed_pyramid_computes_less_and_detects_the_same():
    import cv2
    rng = np.random.default_rng(7)
    img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (3, 3), 1)
    bank = _bank(np.random.default_rng(3), SPECS)
    win = np.array([[60, 50, 110, 90], [200, 150, 240, 190], [20, 20, 60, 60],
                    [250, 30, 300, 70], [100, 120, 150, 170], [np.nan] * 4])
    win[5] = [150, 100, 190, 130]
    levels = [[c.level, c.level + 1] for c in bank]
    part = bank.pyramid(img, levels=levels, windows=win)
    assert part.regions                                     # levels computed only in part
    full = bank.pyramid(img, levels=levels)
    assert not full.regions
    a = bank.detect(part, windows=win, levels=levels)
    b = bank.detect(full, windows=win, levels=levels)
    c = bank.detect(img, windows=win, levels=levels)        # the bank builds the windowed pyramid itself
    for f in ("x", "y", "score", "prob", "level"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        np.testing.assert_array_equal(getattr(c, f), getattr(b, f))
    # Levels described and scored on one thread (the default) or two: the same detections.
    for pyr_or_img in (img, full):
        for wins in (win, None):
            one = bank.detect(pyr_or_img, windows=wins, levels=levels, config={"threads": 1})
            two = bank.detect(pyr_or_img, windows=wins, levels=levels, config={"threads": 2})
            for f in ("x", "y", "score", "prob", "level"):
                np.testing.assert_array_equal(getattr(one, f), getattr(two, f))
    # A partial pyramid refuses windows it was not built for.
    with pytest.raises(ValueError, match="holds features only"):
        bank.detect(part, levels=levels)


def test_blas_limit_nests_and_restores():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from scenesig.signatures.bank import limit_blas_threads

    def counts():
        return [d["num_threads"] for d in threadpoolctl.threadpool_info() if d["user_api"] == "blas"]

    before = counts()
    with limit_blas_threads(1):
        assert set(counts()) == {1}
        with limit_blas_threads(1):          # the same limit again: nothing to set or restore
            assert set(counts()) == {1}
        assert set(counts()) == {1}
    assert counts() == before
