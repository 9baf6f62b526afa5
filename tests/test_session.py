"""The online localiser (``scenesig.Session``): the replay's outputs byte-identical to the recorded ones
(golden digests made in a pinned numerical environment, ``tests/replay_golden.py``), a run fed frame by frame
through the public API equal to the replay, the time rules, the inputs it refuses, and the docs' example.

On the tiny simulated world of ``tests/build_world.py``.
"""
from __future__ import annotations

import json
import platform
import re
from pathlib import Path

import numpy as np
import pytest
from replay_golden import GOLDEN, portable_digests

pytest.importorskip("scenesig.surveys.sim.simulate")

ROOT = Path(__file__).resolve().parents[1]


def _x86_64() -> None:
    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip(f"the golden digests are made with x86-64's baseline kernels (tests/replay_golden.py); "
                    f"this machine is {platform.machine()}")


def _check_golden(got: dict, expected: dict, golden_commit: str) -> None:
    bad = {case: [f for f in got[case] if got[case][f] != expected[case][f]] for case in got}
    bad = {k: v for k, v in bad.items() if v}
    assert not bad, (f"outputs differ from the recording commit's ({golden_commit}): {bad}; if the change of "
                     f"results is intended, regenerate the digests as tests/replay_golden.py says")


def test_replay_outputs_are_mains(tmp_path):
    """localise on the tiny world, every method its map has, with and without INS/GPS: the recorded bytes
    (the world simulated, mapped and localised from nothing in the pinned numerical environment)."""
    _x86_64()
    golden = json.loads(GOLDEN.read_text())
    _check_golden(portable_digests(tmp_path, "cases"), golden["cases"], golden["commit"])


@pytest.mark.heavy
def test_replay_outputs_are_mains_point_layers(tmp_path, xfeat_model, monkeypatch):
    """The same for sift, sift-all, hybrid, hybrid-sift-all and xfeat-all (a map with those layers: ~2 min)."""
    _x86_64()
    monkeypatch.setenv("SCENESIG_XFEAT_MODEL", str(xfeat_model))
    golden = json.loads(GOLDEN.read_text())
    _check_golden(portable_digests(tmp_path, "heavy_cases"), golden["heavy_cases"], golden["commit"])


def _feed(session, run, every: int, gray: bool = True):
    """Feed a recorded run through the public API as a vehicle would: odometry samples in order, each frame
    when its odometry arrived (detector frames to add_image), the estimate at every frame (pose)."""
    odo_t = np.asarray(run.odometry_times, float)
    incs = run.odometry_increments()
    ft = np.asarray(run.frame_times, float)
    poses = np.full((len(ft), 4, 4), np.nan)
    covs = np.full((len(ft), 6, 6), np.nan)
    fixes, states = {}, []

    def frame(i):
        if i % every == 0:
            fix = session.add_image(ft[i], run.image(i, gray=gray))
            if ft[i] > session.t_odometry:
                fix = session.flush()      # after the last odometry sample: held, processed at once
            fixes[i] = fix
        est = session.pose(max(ft[i], odo_t[0]))
        states.append(session.state)
        if est is not None:
            poses[i], covs[i] = est.pose, est.covariance

    session.add_odometry(odo_t[0], np.eye(4))
    fi = 0
    for k in range(1, len(odo_t)):
        session.add_odometry(odo_t[k], incs[k - 1])
        while fi < len(ft) and ft[fi] <= odo_t[k]:
            frame(fi)
            fi += 1
    session.flush()
    while fi < len(ft):
        frame(fi)
        fi += 1
    return poses, covs, fixes, states


@pytest.mark.parametrize("condition,method,oracle,every", [("night", "signatures", "ins", 4),
                                                            ("overcast", "orb", "none", 1)])
def test_session_frame_by_frame_is_the_replay(tiny_world, condition, method, oracle, every):
    from scenesig import Session
    from scenesig.localiser.replay import localise_run

    runs, root = tiny_world
    run = next(r for r in runs if r.conditions[0] == condition)
    result, store = localise_run(root, run.root, method, every=every, oracle=oracle, progress=False)
    ora = (lambda t: run.pose_at(t, "groundtruth")) if oracle == "ins" else None
    with Session(store, run.camera, run.T_vehicle_camera, method, oracle=ora) as s:
        poses, covs, fixes, states = _feed(s, run, every)
    v = np.asarray(result.valid, bool)
    assert v.any()
    assert np.array_equal(np.isfinite(poses[:, 0, 0]), v)
    assert np.array_equal(poses[v], result.poses[v]) and np.array_equal(covs[v], result.covariances[v])
    # a Fix exactly where the replay accepted a localisation (orb: no integrity probation)
    got = np.array([fixes.get(i) is not None for i in range(len(poses))])
    assert np.array_equal(got, np.asarray(result.localised, bool)) and got.sum() > 0
    for i in np.flatnonzero(got):
        f = fixes[i]
        assert f.integrity == "trusted" and f.inliers == result.inliers[i] and f.place == result.places[i]
        assert np.array_equal(f.pose, result.poses[i]) and f.covariance.shape == (6, 6)
        assert f.lateral_bound_95_m > 0
    first = int(np.argmax(got))
    if oracle == "none":        # no INS/GPS: searching until the first fix from the map, tracking after it
        assert set(states[:first]) == {"searching"} and states[first] == "tracking"
    else:
        assert states[0] == "tracking"
    assert set(states) <= {"searching", "tracking", "lost", "alert"}
    assert ("alert" in states) == bool(np.any(result.integrity_alert))   # night signatures: the monitor alerts


def _session(tiny_world, condition="overcast", method="orb", oracle="gnss", **kw):
    from scenesig import Session

    runs, root = tiny_world
    run = next(r for r in runs if r.conditions[0] == condition)
    return Session(root, run.camera, run.T_vehicle_camera, method, oracle=oracle, **kw), run


def test_gnss_oracle_held_late_and_out_of_order_frames(tiny_world):
    s, run = _session(tiny_world)
    odo_t, incs, ft = run.odometry_times, run.odometry_increments(), run.frame_times
    assert s.state == "searching" and s.pose() is None
    s.add_odometry(odo_t[0], np.eye(4))
    assert not s.started                        # no GNSS pose yet: nothing to start from
    for t in run.groundtruth_times[:400]:
        s.add_gnss(t, run.pose_at(t, "groundtruth"))
    s.add_odometry(odo_t[0], np.eye(4))
    assert s.started and s.state == "tracking"
    k = 1
    # a frame ahead of the odometry is held, and localised by the odometry sample that reaches it
    i = int(np.searchsorted(ft, odo_t[0] + 2.0))
    assert s.add_image(ft[i], run.image(i)) is None and s.last_frame is None
    fix = None
    while odo_t[k] < ft[i]:
        assert s.add_odometry(odo_t[k], incs[k - 1]) is None
        k += 1
    fix = s.add_odometry(odo_t[k], incs[k - 1])
    assert s.last_frame is not None and s.last_frame.t == ft[i]
    assert fix is None or fix.t == ft[i]
    while odo_t[k] < ft[i + 4] + 0.1:
        k += 1
        s.add_odometry(odo_t[k], incs[k - 1])
    # late by less than max_latency_s (0.2 s): localised at its own time; later: dropped
    s.add_image(ft[i + 4], run.image(i + 4))
    assert s.last_frame.t == ft[i + 4]
    s.add_image(ft[i + 3], run.image(i + 3))         # out of order, and too late
    assert s.frames_too_late == 1 and s.last_frame.t == ft[i + 4]
    # two frames ahead of the odometry: the newer one waits, the older is dropped
    s.add_image(ft[i + 8], run.image(i + 8, gray=True))
    s.add_image(ft[i + 7], run.image(i + 7))
    assert s.frames_dropped == 1
    s.flush()
    assert s.last_frame.t == ft[i + 8]
    est = s.pose()
    assert est.t == odo_t[k] and est.covariance.shape == (6, 6) and np.isfinite(est.lateral_bound_95_m)
    assert est.state in ("tracking", "lost")
    s.close()
    # out of order within the latency limit (here 0.6 s, two frames of this 4 Hz camera): localised at its time
    s, run = _session(tiny_world, config={"max_latency_s": 0.6})
    for t in run.groundtruth_times:
        s.add_gnss(t, run.pose_at(t, "groundtruth"))
    s.add_odometry(odo_t[0], np.eye(4))
    for k in range(1, int(np.searchsorted(odo_t, ft[i + 2])) + 2):
        s.add_odometry(odo_t[k], incs[k - 1])
    s.add_image(ft[i + 2], run.image(i + 2))
    s.add_image(ft[i + 1], run.image(i + 1))
    assert s.last_frame.t == ft[i + 1] and s.frames_too_late == 0 and s.frames_dropped == 0
    s.close()


def test_session_refuses_bad_input(tiny_world):
    from scenesig import Session
    from scenesig.surveys.geometry import Camera

    s, run = _session(tiny_world, oracle=None)
    with pytest.raises(ValueError, match="oracle='gnss'"):
        s.add_gnss(0.0, np.eye(4))
    s.add_odometry(run.odometry_times[0], np.eye(4))
    with pytest.raises(ValueError, match="time order"):
        s.add_odometry(run.odometry_times[0], np.eye(4))
    with pytest.raises(ValueError, match="rigid"):
        s.add_odometry(run.odometry_times[1], np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="image is 10x10"):
        s.add_image(run.odometry_times[0], np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        s.add_image(run.odometry_times[0], np.zeros((run.camera.height, run.camera.width)))
    with pytest.raises(ValueError, match="finite"):
        s.add_image(float("nan"), run.image(0))
    s.close()
    runs, root = tiny_world
    c = run.camera
    with pytest.raises(ValueError, match="map .* was built from"):
        Session(root, Camera(c.fx, c.fy, c.cx, c.cy, c.width * 2, c.height), run.T_vehicle_camera)
    with pytest.raises(ValueError, match="oracle must be"):
        Session(root, c, run.T_vehicle_camera, oracle="ins")
    with pytest.raises(ValueError, match="unknown session option"):
        Session(root, c, run.T_vehicle_camera, config={"prefetch": True})
    with pytest.raises(Exception, match="sift"):      # the map lacks the method's layer: named
        Session(root, c, run.T_vehicle_camera, method="sift")


def test_preset_reaches_the_session(tiny_world):
    s, run = _session(tiny_world, method="signatures", preset="paper")
    assert s.method.method_config()["prior_gating"] is False
    s.close()


def test_docs_example_runs(tiny_world):
    """docs/api.md's Session example, run as written on the tiny world's map and overcast run."""
    runs, root = tiny_world
    text = (ROOT / "docs" / "api.md").read_text()
    section = text[text.index("## Session"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    run = next(r for r in runs if r.conditions[0] == "overcast")
    scope = {"MAP": str(root), "RUN": str(run.root)}
    exec(compile(code, "docs/api.md", "exec"), scope)
    assert scope["s"].last_frame is not None and scope["est"] is not None
    assert scope["s"].state in ("tracking", "lost", "searching", "alert")

