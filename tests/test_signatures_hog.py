"""FHOG features and the HOG pyramid."""
import numpy as np
import pytest

from signatures import hog


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
