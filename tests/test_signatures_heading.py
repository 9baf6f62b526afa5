"""Signature heading estimation: robust voting, augmentation, and GRIEF data (skipped if absent)."""
import numpy as np
import pytest

from scenesig.signatures import heading


def test_vote_finds_the_dense_mode_not_the_mean():
    rng = np.random.default_rng(0)
    votes = np.r_[rng.normal(50, 3, 30), rng.uniform(-300, 300, 25)]
    est, inl = heading.densest_window_displacement(votes, window=20)
    assert abs(est - 50) < 3
    assert inl[:30].mean() > 0.9 and inl[30:].mean() < 0.2
    # Weights decide between two modes.
    v = np.r_[np.full(5, -100.0), np.full(4, 80.0)]
    w = np.r_[np.full(5, 0.1), np.full(4, 1.0)]
    assert heading.densest_window_displacement(v, w)[0] == 80.0
    assert heading.densest_window_displacement(v)[0] == -100.0
    # No usable vote.
    est, inl = heading.densest_window_displacement(np.array([np.nan, np.nan]))
    assert np.isnan(est) and not inl.any()


def test_augment_keeps_size_and_reports_its_shift():
    rng = np.random.default_rng(1)
    img = np.zeros((60, 120, 3), np.uint8)
    img[:, 40:44] = 255                                # a bright vertical bar at x = 40..43
    for _ in range(5):
        out, shift = heading.augment(img, rng, max_shift=10)
        assert out.shape == img.shape and out.dtype == np.uint8 and abs(shift) <= 10
        col = out.astype(float).mean(axis=(0, 2))
        # The bar moved by the reported shift (it stays the brightest column region).
        assert abs(np.argmax(np.convolve(col, np.ones(4), "valid")) - (40 + shift)) <= 1.5


def _stromovka(grief_root):
    path = grief_root / "stromovka"
    if not path.is_dir():
        pytest.skip(f"{path} not found (needs ../shared/data/grief/stromovka)")
    from scenesig.surveys.grief import load
    return load(path)


def test_leave_one_session_out_bank_on_stromovka(grief_root):
    ds = _stromovka(grief_root)
    pairs = [p for p in ds.pairs() if p.place == 0 and p.live == 3]
    est = heading.SignatureHeading(ds, progress=False)
    out = est.estimate(pairs)
    truth = np.array([ds.truth(p) for p in pairs])
    err = np.abs(np.array(out) - truth)
    assert np.sum(err < 20) >= len(pairs) - 1, err
    # The bank never saw the live session, and the record explains each estimate.
    assert est.bank_stats[0]["live"] == 3
    rec = est.records[tuple(pairs[0])]
    assert rec.fired.sum() >= 10 and rec.inlier.sum() >= 5
    assert rec.map_boxes.shape == rec.live_boxes.shape == (rec.bank_size, 4)


def test_bench_variant_on_learned_cells_estimates_stromovka_and_reports_its_cost(grief_root, xfeat_model,
                                                                                 monkeypatch):
    """``signatures-hog+xfeat`` through the benchmark's method runner: one leave-one-session-out bank, its
    network found where the benchmarks find models (../shared/models) with ``$SCENESIG_XFEAT_MODEL`` unset."""
    from scenesig.benchmarks.heading import SIGNATURE_METHODS, run_signatures
    from scenesig.signatures.xfeat import model_sha256

    monkeypatch.setenv("SCENESIG_XFEAT_MODEL", "")        # restored after the test, whatever the run sets
    monkeypatch.delenv("SCENESIG_XFEAT_MODEL")
    ds = _stromovka(grief_root)
    pairs = [p for p in ds.pairs() if p.place == 0 and p.live == 3]
    r = run_signatures(ds, pairs, progress=False, features=SIGNATURE_METHODS["signatures-hog+xfeat"],
                       name="signatures-hog+xfeat")
    truth = np.array([ds.truth(p) for p in pairs])
    assert np.sum(np.abs(r.estimates - truth) < 20) >= len(pairs) - 1, r.estimates - truth
    assert r.name == "signatures-hog+xfeat" and r.extra["features"] == "hog+xfeat"
    assert r.extra["model_sha256"] == model_sha256(xfeat_model) and r.extra["config"]["mining"]["features"] == "hog+xfeat"
    assert r.extra["live_detect_seconds_per_image"] > 0 and r.extra["mean_mining_seconds"] > 0


@pytest.mark.heavy
def test_stromovka_error_rate_target(grief_root):
    ds = _stromovka(grief_root)
    pairs = list(ds.pairs())
    out = heading.estimate_heading_signatures(ds, pairs, progress=False, n_jobs=2)
    truth = np.array([ds.truth(p) for p in pairs])
    errors = int(np.sum(~(np.abs(np.array(out) - truth) < 20)))
    assert errors <= 3, f"{errors} of {len(pairs)} pairs wrong"


def test_one_configuration_with_a_rule_on_training_data_only():
    """No per-data-set settings: a bank's voting settings depend only on how many real training
    appearances it was mined from (augmented copies do not count)."""
    from scenesig.signatures import heading

    assert not hasattr(heading, "sequence_overrides")
    cfg = dict(heading.default_config)
    many = heading.bank_config(cfg, 11)          # e.g. stromovka: 11 training sessions
    one = heading.bank_config(cfg, 1)            # e.g. season: one summer image (+ augmented copies)
    assert many["calibrated"] and many["min_prob"] == cfg["min_prob"] and many["prob_weight"] == cfg["prob_weight"]
    assert not one["calibrated"] and one["min_prob"] == 0.0 and one["prob_weight"] == 0.0
    assert {k: v for k, v in one.items() if k not in ("min_prob", "prob_weight", "calibrated")} == \
        {k: v for k, v in many.items() if k not in ("min_prob", "prob_weight", "calibrated")}


def test_lopo_revote_is_the_bench_vote():
    """benchmarks.heading_lopo re-weights stored detections: at the configured spread_sigma_px it
    must give exactly the estimate the heading bench voted, and another sigma may change it."""
    from scenesig.benchmarks.heading_lopo import revote
    from scenesig.signatures import heading

    rng = np.random.default_rng(3)
    n, top = 40, 3

    class Det:
        def __init__(self, x, prob):
            self.x, self.prob = x, prob

        def boxes(self, k):
            return np.zeros((len(self.x), 4))

    scale = 0.5
    truth = 30.0
    map_x = rng.uniform(20, 480, (n, 1))
    live_x = map_x + truth * scale + rng.normal(0, 2, (n, top))
    live_x[: n // 3] = rng.uniform(0, 500, (n // 3, top))            # a third vote at random
    det_map = Det(map_x, rng.uniform(0.4, 1.0, (n, 1)))
    det_live = Det(live_x, rng.uniform(0.4, 1.0, (n, top)))
    spread = np.stack([rng.uniform(0, 30, n), rng.uniform(0, 30, n)], axis=1)
    cfg = heading.bank_config(dict(heading.default_config), 11)
    rec = heading._vote_pair(det_map, det_live, cfg, scale, spread)
    assert revote(rec, cfg, cfg["spread_sigma_px"]) == rec.estimate
    assert abs(rec.estimate - truth) < 5
