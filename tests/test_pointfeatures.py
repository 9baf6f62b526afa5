"""Point-feature helpers: upright extraction, match filters, histogram voting."""
import cv2
import numpy as np
import pytest

from scenesig.signatures import pointfeatures as pf


def texture(h=160, w=480, seed=0):
    """Blocky random texture with many corners, lightly blurred."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (h // 8, w // 8), dtype=np.uint8)
    img = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)
    return cv2.GaussianBlur(img, (3, 3), 0)


def _feats(desc, kind="sift"):
    n = len(desc)
    z = np.zeros(n, np.float32)
    return pf.PointFeatures(kind, np.zeros((n, 2), np.float32), z, z, z, np.zeros(n, np.int64),
                            np.asarray(desc, np.float32 if kind != "orb" else np.uint8))


@pytest.mark.parametrize("kind", ["orb", "sift", "rootsift"])
def test_extract_upright_strongest(kind):
    img = texture()
    f = pf.extract(img, kind, n_features=300)
    assert 0 < len(f) <= 300
    assert np.all(f.angle == 0)
    assert np.all(np.diff(f.response) <= 1e-6)  # strongest first
    assert f.descriptors.shape[0] == len(f)
    assert f.descriptors.dtype == (np.uint8 if kind == "orb" else np.float32)
    if kind == "rootsift":
        assert np.allclose((f.descriptors ** 2).sum(axis=1), 1.0, atol=1e-3)
    # No two upright keypoints share position and size (SIFT's orientation copies are dropped).
    keys = {(round(float(x), 2), round(float(y), 2), round(float(s), 2))
            for (x, y), s in zip(f.xy, f.size)}
    assert len(keys) == len(f)


def test_upright_descriptor_ignores_orientation():
    """ORB computed with angle 0 differs from ORB with its own orientation (so 'upright' acts)."""
    img = texture(seed=3)
    up = pf.extract(img, "orb", 200, upright=True)
    rot = pf.extract(img, "orb", 200, upright=False)
    assert np.any(rot.angle != 0)
    assert not np.array_equal(up.descriptors, rot.descriptors)


def test_ratio_dapc_mutual_filters():
    # a0 has a clear match (b0), a1 is equally close to b1 and b2, a2 is far from everything
    # and its nearest neighbour (b1) prefers a1.
    a = _feats([[0, 0], [10, 0], [30, 30]])
    b = _feats([[0.5, 0], [10.2, 0], [9.8, 0], [100, 100]])
    m = pf.match(a, b, "ratio", ratio=0.9)
    assert list(m.query) == [0]
    m = pf.match(a, b, "none")
    assert list(m.query) == [0, 1, 2]
    # dapc: gaps d2 - d1 = 9.3 (a0), 0 (a1), ~0.3 (a2); mean ~3.2 keeps only a0.
    m = pf.match(a, b, "dapc")
    assert list(m.query) == [0]
    m = pf.match(a, b, "none", mutual=True)
    assert set(m.query) == {0, 1}  # a2's nearest neighbour b1 prefers a1


def test_match_empty_and_mismatched():
    a = _feats(np.zeros((0, 2)))
    b = _feats([[1, 2]])
    assert len(pf.match(a, b)) == 0
    with pytest.raises(ValueError, match="cannot match"):
        pf.match(_feats([[1, 2]], "sift"), pf.extract(texture(), "orb", 10))
    with pytest.raises(ValueError, match="unknown match filter"):
        pf.match(b, b, "bogus")


def test_vote_fixed_vs_sliding():
    # A peak of 4 at ~20 straddles the 20-px bin edge; 3 votes sit together at ~51.
    dx = np.array([18, 19, 21, 22, 50, 51, 52, -300.0])
    fixed = pf.histogram_displacement(dx, 20, "fixed")
    slide = pf.histogram_displacement(dx, 20, "sliding")
    assert fixed.support == 3 and fixed.displacement == pytest.approx(51.0)
    assert slide.support == 4 and slide.displacement == pytest.approx(20.0)
    assert list(slide.inliers) == [True] * 4 + [False] * 4
    centre = pf.histogram_displacement(dx, 20, "fixed", estimate="centre", origin=-10)
    assert centre.bin == (10.0, 30.0) and centre.displacement == 20.0
    gated = pf.histogram_displacement(dx, 20, "sliding", dy=np.array([0, 0, 0, 0, 0, 0, 0, 99.0]),
                                 max_dy=50)
    assert gated.n_votes == 7
    none = pf.histogram_displacement(np.array([]))
    assert np.isnan(none.displacement) and none.support == 0


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_estimate_known_shift(kind):
    base = texture(200, 700, seed=7)
    a = base[:, 100:500]
    b = base[:, 63:463]   # a point at column x in a appears at x + 37 in b
    b = cv2.convertScaleAbs(b, alpha=0.8, beta=20)  # a change of exposure
    vote, m = pf.estimate_displacement(pf.extract(a, kind, 500), pf.extract(b, kind, 500))
    assert vote.displacement == pytest.approx(37.0, abs=1.0)
    assert vote.support >= 20 and vote.inliers.sum() == vote.support


def _planted(seed=0, n_true=300, n_false=300, size=(640, 480)):
    """Matches a -> b: ``n_true`` moving together (a smooth motion: a shift and a small zoom),
    ``n_false`` random; descriptors of the true ones agree (small noise), of the false ones not."""
    rng = np.random.default_rng(seed)
    w, h = size
    xa = rng.uniform([0, 0], [w, h], (n_true + n_false, 2))
    xb = np.empty_like(xa)
    xb[:n_true] = (xa[:n_true] - [w / 2, h / 2]) * 1.05 + [w / 2 + 25, h / 2 - 10] + rng.normal(0, 1, (n_true, 2))
    xb[n_true:] = rng.uniform([0, 0], [w, h], (n_false, 2))
    truth = np.arange(n_true + n_false) < n_true
    return xa, xb, truth


def test_gms_keeps_a_planted_consistent_set_and_drops_random_matches():
    from scenesig.signatures.pointfeatures import gms_filter

    xa, xb, truth = _planted()
    keep = gms_filter(xa, xb, (640, 480), (640, 480))
    assert keep[truth].mean() > 0.9, keep[truth].mean()
    assert keep[~truth].mean() < 0.1, keep[~truth].mean()
    # no support without neighbours: random matches alone are all dropped
    assert not gms_filter(xa[~truth], xb[~truth], (640, 480), (640, 480)).any()


@pytest.mark.parametrize("filter", ["gms", "dapc"])
def test_match_filters_keep_planted_matches_and_drop_random_ones(filter):
    """Through :func:`match`: the planted features' descriptors are near copies, the others random."""
    from scenesig.signatures.pointfeatures import PointFeatures, match

    rng = np.random.default_rng(1)
    xa, xb, truth = _planted(seed=1)
    n = len(xa)
    da = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    db = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    flip = rng.random((int(truth.sum()), 32 * 8)) < 0.05          # 5 % of the bits differ
    db[truth] = np.packbits(np.unpackbits(da[truth], axis=1) ^ flip, axis=1)
    z = np.zeros(n, np.float32)

    def feats(xy, d):
        return PointFeatures("orb", xy.astype(np.float32), z, z, z, np.zeros(n, np.int64), d, (480, 640))

    a, b = feats(xa, da), feats(xb, db)
    m = match(a, b, filter=filter, mutual=True, dapc_over="mutual" if filter == "dapc" else "all")
    correct = truth[m.query] & (m.train == m.query)
    assert correct.sum() > 0.9 * truth.sum()
    assert (~correct).sum() < 0.05 * len(m), (~correct).sum()


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_feature_cache_returns_exactly_what_extract_does(kind):
    """A cache hit is the extraction itself (SIFT's descriptors stored as uint8, handed back float32)."""
    img, other = texture(seed=5), texture(seed=6)
    cache = pf.FeatureCache()
    first = cache.extract(img, kind, n_features=300)
    again = cache.extract(img.copy(), kind, n_features=300)           # same bytes, another array
    direct = pf.extract(img, kind, n_features=300)
    assert (cache.misses, cache.hits) == (1, 1)
    for f in (first, again):
        for name in ("xy", "response", "size", "angle", "octave", "descriptors"):
            a, b = getattr(f, name), getattr(direct, name)
            assert a.dtype == b.dtype and np.array_equal(a, b), name
        assert f.kind == direct.kind and f.image_shape == direct.image_shape
    with pytest.raises(ValueError):
        again.xy[0, 0] = -1.0                                         # shared arrays are read-only
    # another image, other settings: misses
    cache.extract(other, kind, n_features=300)
    cache.extract(img, kind, n_features=200)
    cache.extract(img, kind, n_features=300, config={"sift": {"contrastThreshold": 0.01}})
    assert (cache.misses, cache.hits, len(cache)) == (4, 1, 4)


def test_feature_cache_bound_and_scope():
    img = texture(seed=7)
    cache = pf.FeatureCache(max_items=1)
    cache.extract(img, "orb", 100)
    cache.extract(texture(seed=8), "orb", 100)
    cache.extract(img, "orb", 100)
    assert len(cache) == 1 and cache.hits == 0 and cache.misses == 3
    assert pf.active_feature_cache() is None
    with pf.feature_cache() as outer:
        assert pf.active_feature_cache() is outer
        with pf.feature_cache(cache) as inner:
            assert inner is cache and pf.active_feature_cache() is cache
        assert pf.active_feature_cache() is outer
    assert pf.active_feature_cache() is None
