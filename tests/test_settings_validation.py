"""The one settings helper (surveys/settings.py) and the one validation module (surveys/validation.py)."""
import numpy as np
import pytest

from scenesig.surveys.settings import merge_settings
from scenesig.surveys.validation import check_array, check_covariance, check_image, check_pose, check_poses

DEFAULTS = {"a": 1, "sub": {"x": 1.0, "y": 2.0}, "open": {"k": 1}}


def test_merge_is_deep_and_copies():
    out = merge_settings(DEFAULTS, {"sub": {"y": 5.0}, "open": {"anything": 2}}, "demo", open=("open",))
    assert out == {"a": 1, "sub": {"x": 1.0, "y": 5.0}, "open": {"k": 1, "anything": 2}}
    out["sub"]["x"] = 9.0
    assert DEFAULTS["sub"]["x"] == 1.0          # defaults are never modified
    assert merge_settings(DEFAULTS) == DEFAULTS and merge_settings(DEFAULTS) is not DEFAULTS


def test_unknown_keys_are_named_with_the_known_ones():
    with pytest.raises(ValueError, match=r"unknown demo option\(s\) \['b'\]; known: \['a', 'open', 'sub'\]"):
        merge_settings(DEFAULTS, {"b": 1}, "demo")
    with pytest.raises(ValueError, match=r"unknown demo.sub option\(s\) \['z'\]; known: \['x', 'y'\]"):
        merge_settings(DEFAULTS, {"sub": {"z": 1}}, "demo")
    with pytest.raises(TypeError):
        merge_settings(DEFAULTS, [("a", 1)], "demo")


@pytest.mark.parametrize("component", ["scenesig.signatures.hog:build_pyramid", "scenesig.mapping.places:define_places"])
def test_components_reject_unknown_options(component):
    """The two that used to drop (HOG) or accept (places) misspelt options."""
    import importlib

    mod, fn = component.split(":")
    with pytest.raises(ValueError, match="unknown .*option"):
        if fn == "build_pyramid":
            getattr(importlib.import_module(mod), fn)(np.zeros((64, 64), np.uint8), {"cel": 8})
        else:
            getattr(importlib.import_module(mod), fn)(None, {"spacing": 5.0})  # checked before the run is read


def test_pose_and_array_checks():
    T = np.eye(4)
    assert check_pose(T, "T", rigid=True) is not None
    with pytest.raises(ValueError, match="T must be a finite 4x4 pose"):
        check_pose(np.eye(3), "T")
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="not a rigid transform"):
        check_pose(bad, "T", rigid=True)
    assert check_poses(np.stack([T, T]), n=2).shape == (2, 4, 4)
    with pytest.raises(ValueError, match=r"shape \(3, 4, 4\)"):
        check_poses(np.stack([T, T]), "poses", n=3)
    with pytest.raises(ValueError, match="non-finite"):
        check_array([1.0, np.nan], (None,), "x")


def test_covariance_and_image_checks():
    assert np.allclose(check_covariance(np.eye(2), 2), np.eye(2))
    with pytest.raises(ValueError, match="Q must be positive definite"):
        check_covariance(np.diag([1.0, -1.0]), 2, "Q")
    with pytest.raises(ValueError, match="finite 6x6"):
        check_covariance(np.eye(3), 6, "P")
    assert check_image(np.zeros((4, 5, 3), np.uint8), uint8=True).shape == (4, 5, 3)
    with pytest.raises(ValueError, match="uint8"):
        check_image(np.zeros((4, 5)), "keyframe", uint8=True)
    with pytest.raises(ValueError, match="gray or BGR"):
        check_image(np.zeros((4,)), "image")
