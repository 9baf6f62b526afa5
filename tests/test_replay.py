"""``scenesig localise``: outputs, determinism, real-time mode, bad input, and the end-to-end check on the
simulated ``tiny`` world (a map from 4 runs, a held-out day run)."""
import json
import time
from pathlib import Path

import numpy as np
import pytest
from pipeline_world import TruthMethod, make_live_run, make_map

from scenesig.cli import main as cli
from scenesig.localiser.replay import FRAMES_COLUMNS, TIMING_KEYS, localise, replay, write_outputs
from scenesig.surveys.errors import DataError


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("replay_world")
    run = make_live_run(root / "live", length_m=60.0)
    store = make_map(root / "map", length_m=80.0)
    return root, run, store


def _same_outputs(a: Path, b: Path):
    assert (a / "trajectory.tum").read_bytes() == (b / "trajectory.tum").read_bytes()
    assert (a / "frames.csv").read_bytes() == (b / "frames.csv").read_bytes()
    ma, mb = json.loads((a / "metrics.json").read_text()), json.loads((b / "metrics.json").read_text())
    for k in TIMING_KEYS:
        ma.pop(k), mb.pop(k)
    ma.pop("map"), mb.pop("map")
    for m in (ma, mb):      # how frames were loaded (prefetch on a worker or inline) changes no result
        m["settings"]["replay"].pop("prefetch")
    assert ma == mb


def test_outputs(world, tmp_path):
    from evo.tools import file_interface

    root, run, store = world
    res = replay(store, run, TruthMethod(run), every=4)
    m = write_outputs(res, store, tmp_path / "out")
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == ["covariances.csv", "frames.csv", "metrics.json", "trajectory.png",
                                                     "trajectory.tum"]
    traj = file_interface.read_tum_trajectory_file(str(out / "trajectory.tum"))
    assert traj.num_poses == len(run)
    np.testing.assert_allclose(traj.timestamps, run.frame_times, atol=1e-6)
    lines = (out / "frames.csv").read_text().splitlines()
    assert lines[0].split(",") == list(FRAMES_COLUMNS) and len(lines) == len(run) + 1
    rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    assert rows[:, 4].sum() == m["localisations"] == np.ceil(len(run) / 4)     # localised flags
    assert np.all(rows[rows[:, 4] == 1, 2] == 10)                             # detections of those frames
    assert np.median(np.abs(rows[:, 5])) == pytest.approx(m["lateral_error_m"]["median"], abs=1e-6)
    disk = json.loads((out / "metrics.json").read_text())
    for k in ("method", "run", "lateral_error_m", "heading_error_deg", "localised_fraction", "failures",
              "failures_per_km", "blind_fraction_over_20m", "ms_per_detection", "ms_per_solve",
              "ms_per_odometry_update", "realtime_factor"):
        assert k in disk, k
    assert disk["method"] == "truth+noise" and disk["run"] == "live" and disk["failures"] == 0
    assert set(disk["lateral_error_m"]) == {"median", "mean", "p95"}
    assert disk["lateral_error_m"]["median"] < 0.15 and disk["localised_fraction"] == 1.0
    assert disk["realtime_factor"] > 1 and disk["ms_per_odometry_update"] > 0
    assert (out / "trajectory.png").stat().st_size > 20_000


def test_deterministic_replays_are_identical(world, tmp_path):
    root, run, store = world
    for name in ("a", "b"):
        write_outputs(replay(store, run, TruthMethod(run), every=3), store, tmp_path / name, figure=False)
    _same_outputs(tmp_path / "a", tmp_path / "b")


def test_prepare_runs_ahead_on_a_worker_and_changes_nothing(world, tmp_path):
    import threading

    root, run, store = world

    class Prepared(TruthMethod):
        """Truth + noise, with an image-only stage that tags the frame (as feature extraction would)."""

        def __init__(self, run):
            super().__init__(run)
            self.prepare_threads, self.seen = set(), []

        def prepare(self, image):
            self.prepare_threads.add(threading.current_thread().name)
            return ("prepared", image.shape)

        def measure(self, image, place, prior):
            self.seen.append(image)
            return super().measure(image, place, prior)

    ahead, inline = Prepared(run), Prepared(run)
    write_outputs(replay(store, run, ahead, every=3), store, tmp_path / "ahead", figure=False)
    write_outputs(replay(store, run, inline, every=3, config={"prefetch": False}), store, tmp_path / "inline",
                  figure=False)
    _same_outputs(tmp_path / "ahead", tmp_path / "inline")
    # ahead: every detector frame was prepared once, on the worker, and detect got the prepared value
    assert len(ahead.seen) == int(np.ceil(len(run) / 3)) and all(s[0] == "prepared" for s in ahead.seen)
    assert ahead.prepare_threads and all(n.startswith("frame-prefetch") for n in ahead.prepare_threads)
    # inline: the raw image, nothing prepared
    assert not inline.prepare_threads and all(isinstance(s, np.ndarray) for s in inline.seen)


def test_errors_relative_to_a_misplaced_map(world, tmp_path):
    # The map is 3 m off (its reference INS); a localiser that is exact relative to the map is 3 m off
    # the truth -- and 0 m off in the map-relative metrics, which say how far off the map is.
    from scenesig.surveys.geometry import make_pose, rot_z

    root, run, _ = world
    T_off = make_pose(rot_z(np.radians(0.5)), [1.0, -3.0, 0.2])
    store = make_map(tmp_path / "offmap", length_m=80.0, T_map_world=T_off)
    m = write_outputs(replay(store, run, TruthMethod(run, T_map_world=T_off, sigma=[1e-6] * 6), every=1), store,
                      tmp_path / "o", figure=False)
    assert m["lateral_error_m"]["median"] > 2.0
    assert m["lateral_error_map_m"]["median"] < 0.05 and m["heading_error_map_deg"]["median"] < 0.05
    truth_pos = np.array([np.asarray(store.places[i].extra["T_truth_place"])[:, 3] for i in store.places])
    off = np.linalg.norm((truth_pos @ T_off.T)[:, :2] - truth_pos[:, :2], axis=1)
    assert m["map_georeference_error_m"]["median"] == pytest.approx(np.median(off))
    # a map without recorded truth has no map-relative metrics
    m2 = write_outputs(replay(world[2], run, TruthMethod(run), every=4), world[2], tmp_path / "p", figure=False)
    assert "lateral_error_map_m" not in m2


def test_every_sets_the_detector_rate(world):
    root, run, store = world
    for every in (1, 4, 7):
        method = TruthMethod(run)
        res = replay(store, run, method, every=every)
        assert method.calls == res.detector_ran.sum() == len(range(0, len(run), every))
        assert np.array_equal(np.flatnonzero(res.detector_ran), np.arange(0, len(run), every))


class SlowTruth(TruthMethod):
    """Truth + noise, with a detector that takes ``ms`` per frame (two stages, like a real method)."""

    def __init__(self, run, ms):
        super().__init__(run)
        self.ms = ms

    def detect(self, image, place, prior):
        time.sleep(self.ms / 1000.0)
        return prior

    def solve(self, prior, place, _):
        return TruthMethod.measure(self, None, place, prior)


def test_realtime_mode_drops_stale_frames_and_localises(world, tmp_path):
    root, run, store = world
    # 60 m at 9 m/s = 6.7 s of data at 4x: ~1.7 s; a 70 ms detector keeps up with ~3.6 frames/s of
    # data time x4 = ~14 Hz of the 20 Hz camera at best -- frames must be dropped.
    res = replay(store, run, SlowTruth(run, 70.0), realtime=True, speed=4.0)
    m = write_outputs(res, store, tmp_path / "rt", figure=False)
    assert m["mode"] == "realtime" and m["every"] is None
    assert m["frames_dropped"] > 0 and 0 < m["frames_detected"] < len(run)
    assert m["frames_detected"] == res.detector_ran.sum()
    assert m["failures"] == 0 and m["localised_fraction"] > 0.9
    assert m["lateral_error_m"]["median"] < 0.3
    # paced by the data: it cannot run faster than 4x
    assert m["realtime_factor"] < 4.2


def test_cli_signatures_on_a_map_without_signatures_fails_and_resets(world, tmp_path, capsys):
    # Detections withheld for the real method: the map's places hold no signatures.
    root, run, store = world
    out = tmp_path / "cli"
    assert cli(["localise", str(store.root), str(run.root), "--out", str(out), "--every", "2"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["method"] == "signatures" and m["localisations"] == 0
    # the rule on this run's odometry (it over-reads by 2 %): a reset every time 20 m are exceeded
    steps = np.linalg.norm(run.odometry_increments()[:, :3, 3], axis=1)
    expected, c = 0, 0.0
    for d in steps:
        c += d
        if c > 20.0:
            expected, c = expected + 1, 0.0
    # never localised: blind beyond 20 m everywhere past the first 20 m from the known start
    assert m["failures"] == expected == 3
    assert m["blind_fraction_over_20m"] == pytest.approx((m["distance_m"] - 20.0) / m["distance_m"])
    rows = np.loadtxt(out / "frames.csv", delimiter=",", skiprows=1)
    assert rows[:, 7].max() <= 20.5 and rows[:, 2].sum() == 0
    assert m["failures_per_km"] == pytest.approx(3 / (m["distance_m"] / 1000.0))
    assert "lateral_error_m" in capsys.readouterr().out


def test_bad_input_names_the_file(world, tmp_path):
    import shutil

    root, run, store = world
    broken = tmp_path / "noins"
    shutil.copytree(run.root, broken)
    (broken / "groundtruth.tum").unlink()
    with pytest.raises(DataError, match="groundtruth.tum"):
        localise(store.root, broken, tmp_path / "x", method="signatures", progress=False)
    assert cli(["localise", str(store.root), str(broken), "--out", str(tmp_path / "y")]) == 2
    other = make_live_run(tmp_path / "big", length_m=10.0, size=(40, 30))
    with pytest.raises(DataError, match="run.toml.*40x30"):
        localise(store.root, other.root, tmp_path / "z", progress=False)
    with pytest.raises(ValueError, match="every"):
        replay(store, run, TruthMethod(run), every=0)
    with pytest.raises(DataError, match="manifest"):
        localise(tmp_path, run.root, tmp_path / "w", progress=False)


# ------------------------------------------------------------------------------ the tiny world
TRAINING = ["sunny", "overcast", "night", "snow"]


def _tiny_world(root: Path, camera_hz: float, mining: dict | None):
    """Simulate the tiny world (4 training runs + a held-out sunny run) and build its map."""
    pytest.importorskip("scenesig.surveys.sim.simulate")
    from scenesig.mapping.build import build_map
    from scenesig.surveys.run import read_run
    from scenesig.surveys.sim.simulate import simulate

    simulate(root / "runs", preset="tiny", seed=1, runs=TRAINING + ["sunny"], camera_hz=camera_hz, jobs=2,
             show_progress=False)
    names = sorted(p.name for p in (root / "runs").iterdir() if p.is_dir())
    runs = [read_run(root / "runs" / n) for n in names]
    train, live = runs[:4], runs[4]
    assert live.conditions == ["sunny"] and live.name not in [r.name for r in train]
    # the paper's one frame per run (four runs: four images, no augmentation) keeps this test's time;
    # maps from fewer runs are tested in tests/test_fewrun.py
    build_map(train, train[0], root / "map", jobs=2, progress=False,
              config={"frames_per_run": 1, "min_images": 4, **({"mining": mining} if mining else {}),
                      # the point-feature baselines the tests below run
                      "layers": ["signatures", "orb", "sift", "orb-all"]})
    return root / "map", live


@pytest.fixture(scope="module")
def tiny_fast(tmp_path_factory):
    """Tiny world at 5 Hz with a reduced candidate template: the whole chain in about a minute."""
    shapes = {"kinds": [{"name": "square-s", "size": 0.15, "aspect": 1.0, "nx": 8, "ny": 4},
                        {"name": "wide", "size": 0.20, "aspect": 2.0, "nx": 5, "ny": 4},
                        {"name": "tall", "size": 0.20, "aspect": 0.5, "nx": 8, "ny": 3}]}
    return _tiny_world(tmp_path_factory.mktemp("tiny_fast"), 5.0, {"shapes": shapes})


def _check_tiny(map_root, live, out, every):
    m = localise(map_root, live.root, out, every=every, progress=False)
    assert m["failures"] == 0 and m["blind_fraction_over_20m"] == 0.0
    assert m["localised_fraction"] > 0.9
    # Errors relative to the map (its reference run's INS is off by metres: the georeferencing
    # error every place carries, which no localiser can remove -- reported separately)
    assert m["lateral_error_map_m"]["median"] < 0.5, m
    assert m["heading_error_map_deg"]["median"] < 1.0, m
    return m


def test_tiny_world_held_out_day_run_localises(tiny_fast, tmp_path):
    map_root, live = tiny_fast
    _check_tiny(map_root, live, tmp_path / "a", every=1)
    # and a second replay gives the same outputs, with the real detector and solver
    localise(map_root, live.root, tmp_path / "b", every=1, progress=False, figure=False)
    _same_outputs(tmp_path / "a", tmp_path / "b")


@pytest.mark.heavy
def test_tiny_world_full_rate_default_mining(tmp_path_factory, tmp_path):
    map_root, live = _tiny_world(tmp_path_factory.mktemp("tiny_full"), 20.0, None)
    m = _check_tiny(map_root, live, tmp_path / "a", every=4)
    rt = localise(map_root, live.root, tmp_path / "rt", realtime=True, speed=2.0, progress=False)
    assert rt["failures"] == 0 and rt["lateral_error_map_m"]["median"] < 0.5
    assert m["realtime_factor"] > 1.0


@pytest.mark.parametrize("method", ["orb", "sift"])
def test_tiny_world_point_features_localise_the_like_for_like_run(tiny_fast, tmp_path, method):
    """The baselines work where they should: the held-out sunny run against a sunny reference map."""
    map_root, live = tiny_fast
    m = localise(map_root, live.root, tmp_path / method, method=method, every=1, progress=False, figure=False)
    assert m["method"] == method
    assert m["failures"] == 0, m
    assert m["localised_fraction"] >= 0.8, m
    cfg = m["method_config"]
    assert cfg["point_map"] == "reference" and cfg["match"] == "ratio" and cfg["prior_gating"] is True
    assert cfg["n_features"] == 2000 and cfg["min_inliers"] >= 12


def test_demo_job_shares_features_and_places_with_the_same_outputs(tiny_fast, tmp_path):
    """The demo's job for ``orb`` and ``orb-all`` of one run (one live-feature extraction per frame, one
    map store for both replays) writes exactly what two separate localisations write."""
    from scenesig.demo import _localise_group

    map_root, live = tiny_fast
    res = _localise_group(str(map_root), str(live.root.parent), str(tmp_path / "job"), live.name,
                          ["orb", "orb-all"], 1, False)
    assert [(r, e) for r, e, _ in res] == [(live.name, "orb"), (live.name, "orb-all")]
    # the second replay (the first one's features and decoded places) equals a replay on its own
    alone = localise(map_root, live.root, tmp_path / "alone", method="orb-all", every=1, progress=False,
                     figure=False)
    _same_outputs(tmp_path / "alone", tmp_path / "job" / live.name / "orb-all")
    assert res[1][2]["localised_fraction"] == alone["localised_fraction"] > 0.5


def test_tiny_world_kidnapped_start_without_ins(tiny_fast, tmp_path):
    """A run starting mid-route (another ``simulate`` call, same seed), its INS and GPS files removed:
    localised from the map alone, correctly, with no oracle read."""
    from scenesig.surveys.sim.simulate import simulate

    map_root, live = tiny_fast
    simulate(tmp_path / "mid", preset="tiny", seed=1, runs=["night"], camera_hz=5.0, start_m=20.0,
             show_progress=False)
    run = tmp_path / "mid" / "run00_night"
    (run / "groundtruth.tum").unlink()
    (run / "gps.csv").unlink()
    m = localise(map_root, run, tmp_path / "out", every=1, progress=False, oracle="none", figure=False)
    assert m["oracle"] == "none" and m["oracle_reads"] == 0
    assert m["false_fixes"] == 0 and m["failures"] == 0
    assert m["first_fix_m"] is not None and m["first_fix_m"] < 15.0
    assert m["lateral_error_map_m"]["median"] < 0.5, m
    with pytest.raises(DataError, match="groundtruth.tum"):     # the paper's protocol needs the INS
        localise(map_root, run, tmp_path / "ins", every=1, progress=False, oracle="ins", figure=False)
