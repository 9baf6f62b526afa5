"""`scenesig simulate`: valid runs, summary, world description, determinism, errors, place views."""
import hashlib
import json
from argparse import Namespace

import numpy as np
import pytest

from scenesig.commands.simulate import run as run_from_args
from scenesig.surveys.errors import DataError
from scenesig.surveys.run import read_run
from scenesig.surveys.sim import place_views
from scenesig.surveys.sim.simulate import simulate
from scenesig.surveys.sim.world import World

RUNS = ["sunny", "night"]


@pytest.fixture(scope="module")
def sim_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim_a")
    summary = simulate(out, preset="tiny", seed=5, runs=RUNS, camera_hz=2.0, show_progress=False)
    return out, summary


def _digest(folder):
    h = {}
    for f in sorted(folder.rglob("*")):
        if f.is_file() and f.name != "simulate_summary.json":
            h[str(f.relative_to(folder))] = hashlib.sha256(f.read_bytes()).hexdigest()
    return h


def test_summary_and_runs_are_valid(sim_out):
    out, summary = sim_out
    s = json.loads((out / "simulate_summary.json").read_text())
    assert {"runs", "frames", "seconds", "frames_per_second"} <= set(s)
    assert [r["conditions"] for r in s["runs"]] == [[c] for c in RUNS]
    total = 0
    for r in s["runs"]:
        run = read_run(out / r["name"])  # validates every file
        total += len(run)
        assert run.conditions == r["conditions"]
        assert (run.camera.width, run.camera.height) == (320, 240)
        assert run.image(0).shape == (240, 320, 3)
        # every frame lies inside the odometry and INS time ranges
        assert run.odometry_times[0] < run.frame_times[0] and run.odometry_times[-1] > run.frame_times[-1]
        assert run.groundtruth_times[0] < run.frame_times[0] and run.groundtruth_times[-1] > run.frame_times[-1]
        assert abs(np.median(np.diff(run.frame_times)) - 0.5) < 1e-6
        assert abs(np.median(np.diff(run.groundtruth_times)) - 0.1) < 1e-6
        assert abs(np.median(np.diff(run.odometry_times)) - 0.05) < 1e-6
        # INS is a few metres off the truth, not wildly off
        gt = run.pose_at(run.frame_times, "groundtruth")
        err = np.linalg.norm(gt[:, :3, 3] - run.truth_poses[:, :3, 3], axis=1)
        assert err.max() < 15.0
        assert run.metadata["condition"] == r["conditions"][0]
    assert s["frames"] == total > 20
    assert s["frames_per_second"] > 0


def test_world_json_regenerates_the_world(sim_out, tmp_path):
    out, _ = sim_out
    desc = json.loads((out / "world.json").read_text())
    assert desc["preset"] == "tiny" and desc["seed"] == 5
    assert [r["name"] for r in desc["runs"]] == ["run00_sunny", "run01_night"]
    w = World.load(out / "world.json")
    assert w.route.total == pytest.approx(desc["route"]["length_m"], abs=1e-3)
    assert len(w.quads) == desc["n_quads"]
    bad = tmp_path / "bad_world.json"
    bad.write_text(json.dumps(dict(desc, generator_version=-1)))
    with pytest.raises(DataError, match="bad_world.json"):
        World.load(bad)


def test_same_seed_gives_identical_files(sim_out, tmp_path):
    out, _ = sim_out
    simulate(tmp_path, preset="tiny", seed=5, runs=RUNS, camera_hz=2.0, show_progress=False)
    a, b = _digest(out), _digest(tmp_path)
    assert a.keys() == b.keys() and len(a) > 10
    assert a == b


def test_other_seed_gives_another_world(sim_out, tmp_path):
    out, _ = sim_out
    simulate(tmp_path, preset="tiny", seed=6, runs=["sunny"], camera_hz=2.0, show_progress=False)
    a = read_run(out / "run00_sunny").image(3)
    b = read_run(tmp_path / "run00_sunny").image(3)
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 10


def test_parallel_jobs_give_the_same_runs(sim_out, tmp_path):
    out, _ = sim_out
    simulate(tmp_path, preset="tiny", seed=5, runs=RUNS, camera_hz=2.0, jobs=2, show_progress=False)
    assert _digest(out) == _digest(tmp_path)


def test_cli_errors_are_clear(tmp_path, capsys):
    args = Namespace(out=tmp_path / "x", preset="tiny", seed=1, runs="sunny,blizzard", camera_hz=None, jobs=1, overwrite=False)
    assert run_from_args(args) == 2
    assert "blizzard" in capsys.readouterr().err
    args = Namespace(out=tmp_path / "y", preset="tiny", seed=1, runs="sunny", camera_hz=1.0, jobs=1, overwrite=False)
    assert run_from_args(args) == 0
    assert run_from_args(args) == 2  # refuses to overwrite an existing run
    assert "already exists" in capsys.readouterr().err


def test_place_views_show_one_place_under_many_conditions():
    views = place_views("tiny", seed=2, n=4, size=(160, 120))
    assert [c for _, c in views] == ["sunny", "morning", "overcast", "dusk"]
    for img, _ in views:
        assert img.shape == (120, 160, 3) and img.dtype == np.uint8
        assert img.std() > 10  # a scene, not a blank frame
    a, b = views[0][0].astype(int), views[2][0].astype(int)
    assert np.abs(a - b).mean() > 5  # conditions differ


def test_start_m_same_world_other_start(sim_out, tmp_path):
    """A run started mid-route (``--start-m``): the same world (world.json identical apart from its
    ``runs`` entry, which holds the start and the camera rate), the vehicle starts where asked."""
    out, _ = sim_out
    other = tmp_path / "mid"
    simulate(other, preset="tiny", seed=5, runs=["snow"], camera_hz=1.0, start_m=25.0, show_progress=False)
    a, b = json.loads((out / "world.json").read_text()), json.loads((other / "world.json").read_text())
    ra, rb = a.pop("runs"), b.pop("runs")
    assert a == b
    assert rb == [{"name": "run00_snow", "conditions": ["snow"], "camera_hz": 1.0, "start_m": 25.0}]
    assert ra[0]["start_m"] == 0.0 and ra[0]["camera_hz"] == 2.0
    world = World("tiny", 5)
    first = read_run(other / "run00_snow").truth_poses[0, :2, 3]
    # the first frame is taken where the drive starts (after a 1 s lead-in)
    s = world.route.s[np.argmin(np.linalg.norm(world.route.xy - first, axis=1))]
    assert abs(s - 25.0) < 0.5
    start0 = read_run(out / "run00_sunny").truth_poses[0, :2, 3]
    assert abs(world.route.s[np.argmin(np.linalg.norm(world.route.xy - start0, axis=1))]) < 0.5
    with pytest.raises(ValueError, match="start_m"):
        simulate(tmp_path / "bad", preset="tiny", seed=5, runs=["snow"], camera_hz=1.0, start_m=55.0,
                 show_progress=False)
