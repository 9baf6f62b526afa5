"""Integrity monitoring (localiser.integrity) and camera compatibility (mapping.camera_check).

The camera checks run on the tiny simulated world (tests/build_world.py, shared with other modules);
the monitor's decisions on sequences of frame statistics, and the replay's handling of them (a global fix
on probation, an alert that discards it, frames.csv and metrics.json) on the synthetic road of
tests/pipeline_world.py with a weak localiser that answers like scene signatures would on the right map
and on another place's map.  The figures on the demo world are in docs/integrity.md.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from scenesig.cli import main


# ------------------------------------------------------------------------------------------------
# camera compatibility
# ------------------------------------------------------------------------------------------------
def test_compare_cameras_lists_every_difference():
    from scenesig.mapping.camera_check import compare_cameras
    from scenesig.surveys.geometry import Camera, make_pose

    cam = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    T = make_pose(np.eye(3), [1.2, 0.0, 1.5])
    assert compare_cameras(cam, T, cam, T) == []
    other = Camera(575.0, 575.0, 331.0, 246.0, 640, 480)
    found = {f.what: f for f in compare_cameras(other, make_pose(np.eye(3), [1.0, 0.3, 1.75]), cam, T)}
    near = Camera(505.0, 505.0, 322.0, 241.0, 640, 480)            # 1 % and a few pixels: the same camera
    assert compare_cameras(near, T, cam, T) == []
    assert set(found) == {"fx", "fy", "cx", "cy", "extrinsic"}
    assert all(f.severity == "warning" for f in found.values())      # another camera is no reason to refuse
    assert "575, the map's is 500" in found["fx"].reason
    small = Camera(250.0, 250.0, 159.5, 119.5, 320, 240)
    sizes = [f for f in compare_cameras(small, T, cam, T) if f.what == "image size"]
    assert sizes and sizes[0].severity == "error" and "320x240" in sizes[0].reason


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from build_world import tiny_map, tiny_runs

    base = tmp_path_factory.getbasetemp()
    return tiny_map(base), tiny_runs(base)


def _scaled(run, k):
    cam = dataclasses.replace(run.camera, fx=run.camera.fx * k, fy=run.camera.fy * k)
    return dataclasses.replace(run, camera=cam)


def test_rotation_consistency_measures_a_wrong_focal_length(tiny):
    """The images' turns over the odometry's: about 1 with the run's own calibration, about 2 with fx, fy
    halved (the turns look twice as large through half the focal length)."""
    from scenesig.mapping.camera_check import assess, rotation_consistency

    _, runs = tiny
    night = next(r for r in runs if r.conditions[0] == "night")
    ratio, n = rotation_consistency(night)
    assert n >= 5 and abs(ratio - 1.0) < 0.1
    bad, n_bad = rotation_consistency(_scaled(night, 0.5))
    assert n_bad >= 5 and bad > 1.4
    found = assess(_scaled(night, 0.5))
    assert [f.what for f in found.errors] == ["calibration"] and "fx, fy are likely" in found.errors[0].reason
    assert assess(night).findings == []


def _copy_run_scaled(run, dst, k):
    """A copy of a run folder whose run.toml says fx, fy are k times what they are (images linked)."""
    import re

    dst.mkdir()
    for p in run.root.iterdir():
        if p.name == "run.toml":
            text = p.read_text()
            for key in ("fx", "fy"):
                text = re.sub(rf"^{key} = ([0-9.]+)$", lambda m: f"{key} = {float(m.group(1)) * k}", text, flags=re.M)
            (dst / "run.toml").write_text(text)
        else:
            (dst / p.name).symlink_to(p)
    return dst


def test_localise_refuses_a_run_whose_calibration_its_images_contradict(tiny, tmp_path, capsys):
    map_root, runs = tiny
    night = next(r for r in runs if r.conditions[0] == "night")
    bad = _copy_run_scaled(night, tmp_path / "bad", 0.5)
    for oracle in ("none", "ins"):
        out = tmp_path / f"out_{oracle}"
        assert main(["localise", str(map_root), str(bad), "--out", str(out), "--oracle", oracle]) == 2
        err = capsys.readouterr().err
        assert str(bad / "run.toml") in err and "calibration" in err and "Traceback" not in err
        assert not out.exists()                       # nothing written


def test_check_run_map_lists_the_camera_differences(tiny, tmp_path, capsys):
    map_root, runs = tiny
    night = next(r for r in runs if r.conditions[0] == "night")
    assert main(["check", str(night.root), str(map_root)]) == 0     # the map's own camera: nothing to say
    out = capsys.readouterr().out
    assert "camera differs" not in out and "calibration" not in out
    bad = _copy_run_scaled(night, tmp_path / "bad", 0.5)
    assert main(["check", str(bad), str(map_root)]) == 2
    out = capsys.readouterr().out
    assert "camera differs from the map" in out and "fx: 125, the map's is 250 (0.5x)" in out
    assert "error: calibration:" in out


# ------------------------------------------------------------------------------------------------
# the monitor's decisions
# ------------------------------------------------------------------------------------------------
def _stats(t, good=True, solved=True, searched=40, place=3):
    from scenesig.localiser.integrity import FrameStats

    if not solved:
        return FrameStats(t, place, 2, 0, searched, False, np.nan, 1.0, np.nan, np.nan)
    if good:       # the map's own signatures: residuals within their covariance, fixes agree with the odometry
        return FrameStats(t, place, 25, 20, searched, True, 30.0, 34.0, 3.0, 0.1)
    # chance firings of another place's signatures: few, spread over their windows, fixes that jump
    return FrameStats(t, place, 9, 5, searched, True, 30.0, 4.0, 400.0, 4.0)


def test_monitor_confirms_a_good_fix_and_alerts_on_a_bad_one():
    from scenesig.localiser.integrity import IntegrityMonitor

    m = IntegrityMonitor()
    m.begin_probation(0.0)
    # six solved frames, and at two places: a look-alike rarely continues at the next place
    verdicts = [m.assess(_stats(0.2 * k, place=3 + k // 5)) for k in range(1, 9)]
    assert verdicts[:5] == ["tentative"] * 5 and verdicts[5:] == ["accept"] * 3
    assert m.alerts == []
    m = IntegrityMonitor()
    m.begin_probation(0.0)
    assert [m.assess(_stats(0.2 * k)) for k in range(1, 9)] == ["tentative"] * 8     # still one place
    # a look-alike place: the fix's own place fires, the next one hardly (support over the probation)
    m = IntegrityMonitor()
    m.begin_probation(0.0)
    seq = [m.assess(_stats(0.2 * k)) for k in range(1, 4)]
    weak = dict(detections=6, inliers=4)
    from scenesig.localiser.integrity import FrameStats
    seq += [m.assess(FrameStats(1.0 + 0.2 * k, 4, weak["detections"], weak["inliers"], 80, True, 3.0, 2.0, 5.0, 0.3))
            for k in range(3)]
    assert seq[:5] == ["tentative"] * 5 and seq[5] == "alert" and "since the global fix" in m.alerts[0].reason
    m = IntegrityMonitor()
    m.begin_probation(0.0)
    assert m.assess(_stats(0.2, good=False)) == "alert"
    assert len(m.alerts) == 1 and m.alerts[0].place == 3 and "odometry" in m.alerts[0].reason


def test_monitor_alerts_while_tracking_and_recovers_only_on_consistent_frames():
    from scenesig.localiser.integrity import IntegrityMonitor

    m = IntegrityMonitor()
    for t in np.arange(10) * 0.2:
        assert m.assess(_stats(t)) == "accept"          # with INS/GPS: trusted from the start
    verdicts = [m.assess(_stats(2.0 + 0.2 * k, good=False)) for k in range(6)]
    assert "alert" in verdicts and verdicts.count("alert") == 1
    assert verdicts[-1] == "refuse"                             # alerted: no fix accepted
    assert m.assess(_stats(4.0, solved=False)) == "refuse"
    back = [m.assess(_stats(4.2 + 0.2 * k)) for k in range(8)]
    assert back[-1] == "accept" and back[0] == "refuse"


def test_monitor_ignores_methods_it_was_not_calibrated_for():
    from scenesig.localiser.integrity import IntegrityMonitor

    m = IntegrityMonitor(method="orb")
    m.begin_probation(0.0)
    assert m.assess(_stats(0.2, good=False)) == "accept" and m.alerts == []


# ------------------------------------------------------------------------------------------------
# the replay: probation, alerts, outputs (synthetic road, tests/pipeline_world.py)
# ------------------------------------------------------------------------------------------------
class _SignatureLike:
    """What the monitor reads from a scene-signature measurement, on top of test_relocalise's PlaceTruth:
    classifiers searched and the inliers' squared residuals.  ``wrong``: another place's map -- the
    verifications agree with each other (a look-alike stretch passes the sequence check) but the
    tracked fixes are chance firings: residuals at the gate, poses scattered around the prediction."""

    name = "signatures"

    def __init__(self, wrong=False):
        self.wrong = wrong

    def dress(self, m, prior):
        from scenesig.localiser.pipeline import Measurement
        from scenesig.localiser.solver import LocalisationConstraint, pose_exp

        if m is None or m.constraint is None:
            return m
        m.extra = {**m.extra, "searched": 40}
        if not self.wrong:
            m.extra["residual_chi2"] = 1.0 * (2 * m.inliers - 6)
            return m
        if prior.lost:                  # a verification: consistent, as a look-alike's would be
            m.extra["residual_chi2"] = 1.0 * (2 * m.inliers - 6)
            return m
        rng = np.random.default_rng(int(prior.t * 1000))
        c = m.constraint
        T = np.asarray(prior.T_world_vehicle) @ pose_exp(np.r_[0, 0, rng.normal(0, 0.05), rng.normal(0, 3.0, 2), 0])
        cov = c.covariance
        m = Measurement(LocalisationConstraint(T, cov, T, np.linalg.inv(cov)), detections=9, inliers=5, solved=True,
                        extra={"searched": 40, "residual_chi2": 7.0 * 4})
        return m


@pytest.fixture(scope="module")
def road(tmp_path_factory):
    from pipeline_world import make_live_run, make_map

    root = tmp_path_factory.mktemp("integrity_road")
    start = 30.0
    run = make_live_run(root / "live", length_m=120.0, start_m=start, stamp_frames=True)
    store = make_map(root / "map", length_m=160.0)
    return root, run, store, start


def _replay_road(road, wrong):
    from test_relocalise import PlaceTruth, Ranked

    from scenesig.localiser.replay import replay

    _, run, store, start = road
    dress = _SignatureLike(wrong)

    class Method(PlaceTruth):
        name = "signatures"

        def measure(self, image, place, prior):
            return dress.dress(super().measure(image, place, prior), prior)

    method = Method(run, store, start)
    return replay(store, run, method, every=4, oracle="none", retrieval=Ranked(run, store, start))


def test_right_map_is_confirmed_after_probation_without_alert(road, tmp_path):
    from scenesig.localiser.replay import write_outputs

    _, run, store, _ = road
    res = _replay_road(road, wrong=False)
    m = write_outputs(res, store, tmp_path / "out", figure=False)
    assert m["integrity_alerts"] == 0 and m["false_fixes"] == 0 and m["localisations"] > 10
    assert m["localised_fraction"] > 0.8
    header = (tmp_path / "out" / "frames.csv").read_text().splitlines()[0].split(",")
    assert header[header.index("heading_bound_95_deg") + 1] == "integrity_alert"
    # the global fix is tentative: the first localised frame comes after the probation's frames
    first_found = int(np.flatnonzero(np.asarray(res.valid))[0])
    first_localised = int(np.flatnonzero(res.localised)[0])
    assert first_localised > first_found


def test_wrong_map_accepts_no_fix_and_says_so_once(road, tmp_path, caplog):
    import logging

    from scenesig.localiser.replay import write_outputs
    from scenesig.surveys.localisation import Localisation

    _, run, store, _ = road
    with caplog.at_level(logging.WARNING, logger="scenesig.localiser.integrity"):
        res = _replay_road(road, wrong=True)
    said = [r for r in caplog.records if "integrity alert" in r.getMessage()]
    assert len(said) == 1 and "near the map's place" in said[0].getMessage()
    m = write_outputs(res, store, tmp_path / "out", figure=False)
    assert m["localisations"] == 0 and m["integrity_alerts"] >= 1 and m["integrity_alert_frames"] >= 1
    assert m.get("first_fix_time") is None           # no fix was ever confirmed
    frames = Localisation.from_folder(tmp_path / "out").frames
    assert frames["integrity_alert"].sum() == m["integrity_alert_frames"]
    assert not np.asarray(res.valid).any()           # the discarded fixes left no pose behind
