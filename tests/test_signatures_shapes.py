"""The candidate-shape template."""
import numpy as np
import pytest

from scenesig.signatures.shapes import candidate_shapes, default_config


@pytest.mark.parametrize("size", [(640, 480), (1024, 384), (512, 192)])
def test_default_template_has_296_shapes_inside_the_image(size):
    w, h = size
    s = candidate_shapes(w, h)
    assert len(s) == 296
    b = s.boxes
    assert np.all(b[:, 0] >= 0) and np.all(b[:, 1] >= 0)
    assert np.all(b[:, 0] + b[:, 2] <= w) and np.all(b[:, 1] + b[:, 3] <= h)
    # Tall and wide strips are present, and positions span the image.
    ar = b[:, 2] / b[:, 3]
    assert ar.max() >= 4 and ar.min() <= 0.25
    cx = b[:, 0] + b[:, 2] / 2
    assert cx.min() < 0.15 * w and cx.max() > 0.85 * w


def test_squares_stay_square_and_cover_the_same_area_fraction():
    a = candidate_shapes(640, 480)
    b = candidate_shapes(1024, 384)
    sq = a.kind == a.kind_names.index("square-m")
    assert np.allclose(a.boxes[sq, 2], a.boxes[sq, 3])
    fa = (a.boxes[:, 2] * a.boxes[:, 3]).sum() / (640 * 480)
    fb = (b.boxes[:, 2] * b.boxes[:, 3]).sum() / (1024 * 384)
    assert abs(fa - fb) / fa < 0.1


def test_configurable_and_validated():
    cfg = {"kinds": [{"name": "x", "size": 0.2, "aspect": 1.0, "nx": 3, "ny": 2}]}
    s = candidate_shapes(320, 240, cfg)
    assert len(s) == 6 and s.kind_names == ("x",)
    with pytest.raises(ValueError, match="lacks"):
        candidate_shapes(320, 240, {"kinds": [{"size": 0.2, "nx": 1, "ny": 1}]})
    with pytest.raises(ValueError):
        candidate_shapes(320, 240, {"kinds": []})
    assert sum(k["nx"] * k["ny"] for k in default_config["kinds"]) == 296
