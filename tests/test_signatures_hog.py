"""FHOG features and the HOG pyramid."""
import numpy as np
import pytest

from scenesig.signatures import hog


def _edge_image(vertical=True, h=64, w=96):
    img = np.zeros((h, w), np.uint8)
    if vertical:
        img[:, w // 2:] = 200          # intensity rises along +x: gradient angle 0 deg
    else:
        img[h // 2:, :] = 200          # rises along +y: gradient angle 90 deg
    return img


def test_shape_and_range():
    f = hog.fhog(np.random.default_rng(0).integers(0, 255, (100, 130), dtype=np.uint8))
    assert f.shape == (12, 16, hog.FEATURE_DIM) and f.dtype == np.float32
    assert np.all(f >= 0) and np.all(np.isfinite(f))
    # Clipped, normalised bins: each of the 4 normalisations contributes at most 0.2 * 0.5.
    assert f[:, :, :27].max() <= 4 * 0.5 * 0.2 + 1e-6


def test_orientation_bins_follow_the_gradient():
    fv = hog.fhog(_edge_image(True))
    fh = hog.fhog(_edge_image(False))
    # Cells on the edge: the strongest contrast-sensitive bin is 0 (0 deg) / 4-5 (90 deg).
    col = fv[:, 5:7, :18].sum(axis=(0, 1))
    row = fh[3:5, :, :18].sum(axis=(0, 1))
    assert int(np.argmax(col)) in (0, 17, 1)
    assert int(np.argmax(row)) in (4, 5)
    # Flipping the contrast moves the sensitive bin by 180 deg but keeps the insensitive one.
    fneg = hog.fhog(255 - _edge_image(True))
    assert int(np.argmax(fneg[:, 5:7, :18].sum(axis=(0, 1)))) in (8, 9, 10)
    np.testing.assert_allclose(fneg[:, :, 18:27], fv[:, :, 18:27], atol=1e-5)
    # Far from the edge there is no gradient at all.
    assert fv[:, 0, :27].max() < 1e-3


def test_contrast_invariance():
    rng = np.random.default_rng(1)
    img = rng.integers(30, 120, (80, 96)).astype(np.uint8)
    a = hog.fhog(img)
    b = hog.fhog((img.astype(np.float32) * 2.0).astype(np.uint8))
    assert np.abs(a - b).max() < 0.02


def test_colour_input_and_validation():
    rng = np.random.default_rng(2)
    bgr = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    assert hog.fhog(bgr).shape == (6, 8, 31)
    assert hog.fhog(bgr, color=True).shape == (6, 8, 31)
    with pytest.raises(ValueError):
        hog.fhog(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError):
        hog.fhog(np.zeros((40, 40, 2), np.uint8))
    with pytest.raises(ValueError):
        hog.fhog(np.zeros((40, 40), np.uint8), cell=7)


def test_pyramid_levels_and_coordinates():
    img = np.random.default_rng(3).integers(0, 255, (240, 320), dtype=np.uint8)
    pyr = hog.build_pyramid(img, levels=[0, 2, 4])
    assert sorted(pyr.levels) == [0, 2, 4]
    assert pyr.levels[0].shape[:2] == (30, 40)
    assert pyr.sizes[4] == (160, 120)
    assert abs(pyr.scale(2) - 2 ** -0.5) < 0.01
    # window_centre and cell_at are inverse maps.
    x, y = pyr.window_centre(2, 3.25, 5.5, 4, 6)
    r, c = pyr.cell_at(2, x, y, 4, 6)
    assert abs(r - 3.25) < 1e-9 and abs(c - 5.5) < 1e-9
    # At level 0 a 2x2-cell window at cell (0, 0) covers pixels 0..15: centre 7.5.
    assert pyr.window_centre(0, 0, 0, 2, 2) == (7.5, 7.5)
    assert pyr.matches(hog.default_config)
    assert not pyr.matches({**hog.default_config, "cell": 4})


def test_pyramid_feature_of_level_equals_fhog_of_resized_image():
    import cv2
    img = np.random.default_rng(4).integers(0, 255, (120, 160), dtype=np.uint8)
    pyr = hog.build_pyramid(img, levels=[1])
    w, h = pyr.sizes[1]
    ref = hog.fhog(cv2.resize(img.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA))
    np.testing.assert_allclose(pyr.levels[1], ref, atol=1e-6)


def _textured(h=240, w=320, seed=4):
    import cv2
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.integers(0, 255, (h, w), dtype=np.uint8), (5, 5), 1.2)


@pytest.mark.parametrize("color", [False, True])
def test_resize_area_region_equals_the_crop_of_the_opencv_resize(color):
    import cv2
    img = _textured()
    if color:
        img = np.dstack([img, img[::-1], 255 - img])
    f = hog.to_gray_float(img, color)
    for k in (1, 2, 3, 4, 5):                     # non-integer and integer (level 4: /2) factors
        size = hog.level_size((320, 240), k, 4)
        full = cv2.resize(f, size, interpolation=cv2.INTER_AREA)
        for rows, cols in (((0, size[1]), (0, size[0])), ((7, 40), (13, 90)), ((size[1] - 9, size[1]), (0, 5))):
            part = hog.resize_area_region(f, size, rows, cols)
            assert np.array_equal(part, full[rows[0]:rows[1], cols[0]:cols[1]])
    with pytest.raises(ValueError):
        hog.resize_area_region(f, (400, 300), (0, 10), (0, 10))      # upscaling
    with pytest.raises(ValueError):
        hog.resize_area_region(f, (160, 120), (0, 130), (0, 10))     # outside the resized image


def test_pyramid_regions_hold_exactly_the_whole_levels_features():
    img = _textured()
    full = hog.build_pyramid(img, levels=[0, 1, 3, 4])
    boxes = {0: (10, 14, 20, 26), 1: (0, 5, 0, 7), 3: (8, 17, 15, 20), 4: (3, 6, 9, 14)}
    part = hog.build_pyramid(img, levels=[0, 1, 3, 4], regions=boxes)
    for k, (r0, r1, c0, c1) in boxes.items():
        e0, e1, g0, g1 = part.valid_region(k)
        assert e0 <= r0 and e1 >= r1 and g0 <= c0 and g1 >= c1        # at least what was asked
        assert part.levels[k].shape == full.levels[k].shape
        assert np.array_equal(part.levels[k][e0:e1, g0:g1], full.levels[k][e0:e1, g0:g1])
        assert (e1 - e0) * (g1 - g0) < full.levels[k].shape[0] * full.levels[k].shape[1]
        assert not part.levels[k][:e0].any() and not part.levels[k][e1:].any()   # nothing else computed
    # A region covering most of its level is computed whole.
    whole = hog.build_pyramid(img, levels=[2], regions={2: (0, 20, 0, 28)})
    assert 2 not in whole.regions and whole.valid_region(2) == (0,) + whole.levels[2].shape[:1] + (0, whole.levels[2].shape[1])


def test_thread_map_keeps_order_raises_and_nests():
    import cv2
    cv_threads = set()
    before = cv2.getNumThreads()

    def square(x):
        cv_threads.add(cv2.getNumThreads())
        return x * x

    items = list(range(9))
    # the library alone leaves OpenCV's threads as they are ...
    assert hog.thread_map(square, items, threads=2, cost=items) == [x * x for x in items]
    assert cv_threads == {before}
    # ... the command line's runtime layer runs the threads with OpenCV on one thread, and restores it
    from scenesig.runtime import opencv_single_threaded

    cv_threads.clear()
    hog.set_parallel_section(opencv_single_threaded)
    try:
        assert hog.thread_map(square, items, threads=2, cost=items) == [x * x for x in items]
    finally:
        hog.set_parallel_section(None)
    assert cv_threads == {1} and cv2.getNumThreads() == before
    assert hog.thread_map(square, items, threads=1) == [x * x for x in items]
    assert hog.thread_map(square, [], threads=2) == []

    def boom(x):
        if x == 3:
            raise KeyError("three")
        return x

    with pytest.raises(KeyError, match="three"):
        hog.thread_map(boom, items, threads=2)
    # nested calls (each with helper threads of its own)
    assert hog.thread_map(lambda x: sum(hog.thread_map(square, range(x), threads=2)), [3, 4], threads=2) == [5, 14]
    assert cv2.getNumThreads() == before


@pytest.mark.parametrize("threads", [2, 3])
def test_pyramid_on_threads_equals_the_serial_pyramid(threads):
    img = _textured()
    boxes = {0: (10, 14, 20, 26), 3: (8, 17, 15, 20)}
    for regions in (None, boxes):
        a = hog.build_pyramid(img, levels=[0, 1, 3, 4, 6], regions=regions)
        b = hog.build_pyramid(img, levels=[0, 1, 3, 4, 6], regions=regions, threads=threads)
        assert a.levels.keys() == b.levels.keys() and a.regions == b.regions and a.sizes == b.sizes
        for k in a.levels:
            assert np.array_equal(a.levels[k], b.levels[k])


def test_thread_map_works_in_a_forked_child():
    import multiprocessing as mp
    import os

    if not hasattr(os, "fork"):
        pytest.skip("no fork on this platform")
    hog.thread_map(abs, [1, -2, 3], threads=2)            # the parent's pool exists now
    with mp.get_context("fork").Pool(1) as pool:
        assert pool.apply(hog.thread_map, (abs, [-1, -2, -3], 2)) == [1, 2, 3]


def _numpy_fhog(monkeypatch, *args):
    with monkeypatch.context() as m:
        m.setattr(hog, "_NUMPY_ONLY", True)
        return hog.fhog(*args)


@pytest.mark.skipif(not hog._hog_kernel.AVAILABLE, reason="numba is not installed: fhog runs in numpy only")
@pytest.mark.parametrize("color", [False, True])
def test_compiled_fhog_equals_the_numpy_fhog_bit_for_bit(monkeypatch, color):
    rng = np.random.default_rng(3)
    images = [_textured(240, 320, seed=4), rng.integers(0, 256, (123, 77), dtype=np.uint8),
              rng.integers(0, 256, (8, 8), dtype=np.uint8), _edge_image(), np.zeros((40, 48), np.uint8),
              np.full((33, 65), 255, np.uint8)]
    for img in images:
        if color:
            img = np.dstack([img, img[::-1], 255 - img])
        for clip in (0.2, 0.1):
            a = hog.fhog(img, 8, clip, color)
            b = _numpy_fhog(monkeypatch, img, 8, clip, color)
            assert a.dtype == b.dtype == np.float32 and np.array_equal(a, b)
    # A camera view of textured planes: every other level of its pyramid.
    import cv2
    from point_world import camera_pose, render, vehicle_pose
    frame = hog.to_gray_float(render(camera_pose(vehicle_pose(2.0, 0.3, 0.05)))[0])
    for k in range(0, 9, 2):
        size = hog.level_size(frame.shape[1::-1], k, 4)
        lvl = frame if k == 0 else cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
        assert np.array_equal(hog.fhog(lvl), _numpy_fhog(monkeypatch, lvl))


def test_scaled_images_give_the_same_pyramid_regions_as_the_image():
    img = _textured(240, 320, seed=5)
    cfg = dict(hog.default_config)
    scaled = hog.ScaledImages.for_pyramid(img, cfg)
    assert scaled.resized((320, 240)) is scaled.image and scaled.resized((7, 7)) is None
    regions = {0: (3, 12, 5, 20), 1: (0, 9, 0, 30), 3: (8, 14, 10, 18), 5: (0, 100, 0, 100)}
    a = hog.build_pyramid(img, cfg, levels=[0, 1, 3, 5, 6], regions=regions)
    b = hog.build_pyramid(scaled, cfg, levels=[0, 1, 3, 5, 6], regions=regions)
    assert a.regions == b.regions and sorted(a.levels) == sorted(b.levels)
    for k in a.levels:
        assert np.array_equal(a.levels[k], b.levels[k])
    # Levels described whole are kept, and later regions of them are taken from there.
    whole = hog.build_pyramid(scaled, cfg, levels=[0, 1, 3, 5, 6])
    assert scaled.features(scaled.resized((320, 240)).shape[1::-1], cfg) is whole.levels[0]
    again = hog.build_pyramid(scaled, cfg, levels=[0, 1, 3, 5, 6], regions=regions)
    assert again.regions == a.regions
    for k in a.levels:
        assert np.array_equal(a.levels[k], again.levels[k])
    assert scaled.features((320, 240), dict(cfg, clip=0.1)) is None        # other HOG parameters
    with pytest.raises(ValueError, match="color"):
        hog.build_pyramid(scaled, {"color": True})
