"""The one localisation type (``scenesig.surveys.localisation.Localisation``): ``write`` then ``from_folder``
gives the same arrays, typed columns and metrics; a missing or corrupt file is a DataError naming it."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scenesig.surveys.errors import DataError
from scenesig.surveys.localisation import FRAMES_COLUMNS, Localisation


def _loc(oracle: str = "ins") -> Localisation:
    n = 6
    t = 10.0 + 0.25 * np.arange(n)
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, 0, 3] = np.arange(n) * 1.5
    valid = np.ones(n, bool)
    if oracle == "none":
        valid[:2] = False            # before the first fix: no pose
        P[~valid] = np.nan
    planar = np.tile(np.diag([0.04, 0.09, 0.001]), (n, 1, 1))
    planar[~valid] = np.nan
    frames = {"place": [0, 0, 1, 1, 2, 2], "detections": [3, 0, 4, 0, 5, 0], "inliers": [2, 0, 3, 0, 4, 0],
              "localised": [1, 0, 1, 0, 0, 0], "distance_since_localisation": [0, 0.4, 0, 0.4, 0.8, 1.2],
              "lateral_error": [0.1, 0.2, np.nan, 0.1, 0.3, 0.1], "integrity_alert": [0, 0, 0, 0, 1, 0],
              "signature_inliers": [2, 0, 3, 0, 4, 0]}
    metrics = {"method": "signatures", "run": "r", "oracle": oracle, "failures": 1, "reset_times": [11.1],
               "relocalisation_times": [[10.2, 10.6]], "every": 2, "mode": "deterministic"}
    return Localisation(method="signatures", every=2, times=t, poses=P, valid=valid, frames=frames,
                        planar_covariances=planar, metrics=metrics, oracle=oracle)


@pytest.mark.parametrize("oracle", ["ins", "none"])
def test_write_then_from_folder(tmp_path, oracle):
    loc = _loc(oracle)
    assert loc.write(tmp_path / "out") == loc.metrics
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["covariances.csv", "frames.csv", "metrics.json",
                                                                      "trajectory.tum"]
    back = Localisation.from_folder(tmp_path / "out")
    assert back.metrics == loc.metrics and back.method == "signatures" and back.oracle == oracle
    assert list(back.frames) == list(FRAMES_COLUMNS)
    for k, v in loc.frames.items():
        assert back.frames[k].dtype == v.dtype, k
        assert np.array_equal(back.frames[k], v, equal_nan=v.dtype.kind == "f"), k
    assert back.localised.dtype == bool and back.places.dtype.kind == "i"
    assert np.array_equal(back.valid, loc.valid) and np.allclose(back.times, loc.times)
    assert np.allclose(back.poses, loc.poses, equal_nan=True)
    assert np.allclose(back.planar_covariances, loc.planar_covariances, equal_nan=True)
    assert back.resets.tolist() == [False] * 5 + [True]      # the first frame after the reset time
    assert back.failures == 1 and back.relocalisations == [(10.2, 10.6)]
    # written again it is the same bytes
    back.write(tmp_path / "again")
    for name in ("trajectory.tum", "covariances.csv", "frames.csv", "metrics.json"):
        assert (tmp_path / "again" / name).read_bytes() == (tmp_path / "out" / name).read_bytes(), name
    assert back.digest() == Localisation.from_folder(tmp_path / "again").digest()


def test_from_folder_names_the_bad_file(tmp_path):
    out = tmp_path / "out"
    _loc().write(out)
    with pytest.raises(DataError, match="metrics.json: missing"):
        Localisation.from_folder(tmp_path)
    (out / "frames.csv").write_text("time,place\n1,2\n")
    with pytest.raises(DataError, match="frames.csv.*missing column"):
        Localisation.from_folder(out)
    _loc().write(out)
    (out / "covariances.csv").write_text("time,xx\n")
    with pytest.raises(DataError, match="covariances.csv"):
        Localisation.from_folder(out)
    _loc().write(out)
    (out / "trajectory.tum").unlink()
    with pytest.raises(DataError, match="trajectory.tum: missing"):
        Localisation.from_folder(out)
    _loc().write(out)
    (out / "metrics.json").write_text("{")
    with pytest.raises(DataError, match="metrics.json:1: invalid JSON"):
        Localisation.from_folder(out)
    (out / "metrics.json").write_text(json.dumps({"method": "signatures"}))
    with pytest.raises(DataError, match="at least 'method' and 'run'"):
        Localisation.from_folder(out)


def test_write_needs_the_metrics(tmp_path):
    loc = _loc()
    loc.metrics = None
    with pytest.raises(ValueError, match="no metrics"):
        loc.write(tmp_path / "out")
