"""Every benchmark of ``scenesig bench`` runs, on tiny inputs, in the default suite.

One test per entry of :data:`scenesig.commands.bench.BENCHMARKS` (a benchmark added without a smoke test
here fails :func:`test_every_benchmark_has_a_smoke_test`).  Each runs the benchmark's ``main`` (or, where
``main`` has no switch small enough, its run function with a cut-down configuration), and checks that it
returns 0 and prints or writes the JSON of what it measured.  The inputs: the tiny simulated world of
``tests/build_world.py`` (three runs and its map), a few frames copied from ``../shared/data`` into a
temporary folder (those tests skip without the shared data), synthetic problems.  Figures are not
checked here -- only that nothing is broken.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from build_world import CONFIG, SHAPES
from conftest import SHARED_DATA

from scenesig.commands.bench import BENCHMARKS

#: a cut-down candidate template (the tiny world's) for the benchmarks that mine banks
TINY_MINING = {"shapes": SHAPES, "n_partitions": 2}


def _shared(*parts) -> Path:
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not found at {path} (../shared/data beside the project)")
    return path


def _last_json(text: str):
    """The last JSON document printed (benchmarks print a table or progress first, some)."""
    text = text.strip()
    for start in [i for i, c in enumerate(text) if c in "{["][::-1]:
        try:
            return json.loads(text[start:])
        except json.JSONDecodeError:
            continue
    raise AssertionError(f"no JSON in the output: {text[-500:]!r}")


def _run(name, argv, capsys, json_path: Path | None = None):
    import importlib

    module = importlib.import_module(f"scenesig.benchmarks.{BENCHMARKS[name][0]}")
    assert int(module.main([str(a) for a in argv]) or 0) == 0
    out = capsys.readouterr().out
    doc = json.loads(Path(json_path).read_text()) if json_path is not None else _last_json(out)
    assert doc, f"{name}: empty JSON"
    return doc


def _frames(run, k: int, every: int = 1) -> list[Path]:
    return [run.root / f for f in run.frame_files[::every][:k]]


# ------------------------------------------------------------------------------- synthetic inputs
def test_absolute_pose(capsys):
    _run("absolute-pose", ["--matches", "40", "--repeats", "2"], capsys)


def test_hog(capsys):
    _run("hog", ["--levels", "2"], capsys)


def test_posegraph(capsys):
    _run("posegraph", ["--seconds", "3"], capsys)


def test_refine(capsys):
    _run("refine", ["--landmarks", "10", "--frames", "5", "--random", "2"], capsys)


def test_solver(capsys):
    _run("solver", ["--detections", "10", "--repeats", "2"], capsys)


def test_strict_decode(capsys):
    _run("strict_decode", ["--frames", "2", "--repeats", "1", "--trials", "2"], capsys)


def test_render(capsys):
    _run("render", ["--preset", "tiny", "--frames", "2", "--conditions", "sunny"], capsys)


def test_realism(tmp_path, capsys):
    _run("realism", ["--preset", "tiny", "--places", "2", "--json", tmp_path / "r.json"], capsys, tmp_path / "r.json")


def test_simcam(tmp_path, capsys):
    _run("simcam", [tmp_path / "cams", "--places", "1", "--json", tmp_path / "s.json"], capsys, tmp_path / "s.json")


def test_speed(monkeypatch, capsys):
    from scenesig.benchmarks import speed
    from scenesig.signatures import mining

    real = mining.mine_place
    monkeypatch.setattr(mining, "mine_place", lambda *a, **k: real(*a, **{**k, "config": TINY_MINING}))
    monkeypatch.setattr(speed, "place_images", _small(speed.place_images))
    _run("speed", ["--train-repeats", "1"], capsys)


def _small(place_images):
    """The speed benchmark's place images, six of them (its mining is cut down separately)."""
    return lambda n=31, seed=0: place_images(6, seed)


# ------------------------------------------------------------------------- the tiny world and its map
def test_detector(tiny_world, capsys):
    runs, root = tiny_world
    _run("detector", [root, runs[2].root, "--frames", "2"], capsys)


def test_pointmap(tiny_world, capsys):
    runs, _ = tiny_world
    _run("pointmap", [runs[0].root, "--frame", "4", "--window-m", "3"], capsys)


def test_mining(tiny_world, capsys, monkeypatch, tmp_path):
    from scenesig.signatures import mining

    runs, _ = tiny_world
    real = mining.mine_place
    monkeypatch.setattr(mining, "mine_place", lambda *a, **k: real(*a, **{**k, "config": TINY_MINING}))
    images = [p for r in runs for p in _frames(r, 2, every=3)]
    _run("mining", [*images, "--out", tmp_path / "bank.npz"], capsys)
    assert (tmp_path / "bank.npz").is_file()


def test_profile_mining(tiny_world, capsys):
    runs, _ = tiny_world
    images = [p for r in runs for p in _frames(r, 2, every=3)]
    _run("profile_mining", ["--images", *images, "--shapes", "4"], capsys)


def test_profile_localise(tiny_world, tmp_path, capsys):
    runs, root = tiny_world
    _run("profile_localise", [root, runs[2].root, "--every", "8", "--json", tmp_path / "p.json"], capsys,
         tmp_path / "p.json")


def test_relocalise(tiny_world, tmp_path, capsys):
    runs, root = tiny_world
    _run("relocalise", [root, runs[2].root, "--places", "4,8", "--frames", "2", "--json", tmp_path / "r.json"],
         capsys, tmp_path / "r.json")


def test_uncertainty(tiny_world, tmp_path, capsys):
    from scenesig.localiser.replay import localise

    runs, root = tiny_world
    localise(root, runs[2].root, tmp_path / "loc", every=8, progress=False, figure=False)
    _run("uncertainty", [tmp_path / "loc", "--factors", "1,2"], capsys)


def test_hybrid_calibration(tiny_world, tmp_path, capsys):
    runs, root = tiny_world         # the tiny map holds ORB keyframes (tests/build_world.py)
    doc = _run("hybrid_calibration", [root, runs[2].root, "--points", "orb", "--every", "8",
                                      "--json", tmp_path / "h.json"], capsys, tmp_path / "h.json")
    assert "config" in doc


def test_rosbag_import(tiny_world, capsys):
    pytest.importorskip("rosbags")
    runs, _ = tiny_world
    _run("rosbag-import", [runs[0].root, "--frames", "4", "--formats", "mcap", "--images", "raw", "--repeats", "1"],
         capsys)


@pytest.mark.heavy
def test_rosbag_roundtrip(tiny_world, tmp_path, monkeypatch, capsys):
    """The round trip's benchmark on the tiny world (its three runs already simulated, not four).  Heavy: 100 s
    on the 2-core CI machine; the round trip itself (every format, images, odometry, covariances) is checked
    in the default suite by tests/test_rosbag.py."""
    pytest.importorskip("rosbags")
    from scenesig.benchmarks import rosbag_roundtrip

    runs, _ = tiny_world
    (tmp_path / "world").mkdir()
    for r in runs:
        shutil.copytree(r.root, tmp_path / "world" / r.root.name)
    # its live run is a fog run: the night run, renamed, stands in for it
    night = next(r for r in runs if r.conditions[0] == "night")
    fog = tmp_path / "world" / "run03_fog"
    shutil.copytree(night.root, fog)
    toml = (fog / "run.toml").read_text()
    (fog / "run.toml").write_text(toml.replace(f'name = "{night.name}"', 'name = "run03_fog"')
                                  .replace('conditions = ["night"]', 'conditions = ["fog"]'))
    (tmp_path / "world" / "simulate_summary.json").write_text("{}")
    monkeypatch.setattr(rosbag_roundtrip, "CONFIG", {**CONFIG, "points": {**CONFIG["points"], "max_points": 50}})
    doc = _run("rosbag-roundtrip", ["--work", tmp_path, "--json", tmp_path / "rt.json"], capsys, tmp_path / "rt.json")
    assert doc


def test_demo_localise(tiny_world, tmp_path, capsys):
    """The demo's localisation stage on a demo-shaped folder made of the tiny world (one live run, the
    cheapest entry)."""
    from scenesig.demo import default_config

    runs, root = tiny_world
    demo = tmp_path / "demo"
    (demo / "world").mkdir(parents=True)
    for r in runs:
        (demo / "world" / r.root.name).symlink_to(r.root)
    (demo / "map").symlink_to(root)
    (demo / "world" / "simulate_summary.json").write_text(json.dumps(
        {"runs": [{"name": r.name} for r in runs]}))
    cfg = {"training": [r.conditions[0] for r in runs], "reference": runs[0].conditions[0],
           "methods": ["signatures"], "no_oracle_methods": [], "camera_hz": 4.0, "detector_hz": 1.0}
    assert set(cfg) <= set(default_config)
    (demo / "summary.json").write_text(json.dumps({"config": cfg, "runs": [{"run": runs[2].name}]}))
    doc = _run("demo_localise", [demo, "--out", tmp_path / "out", "--jobs", "1", "--json", tmp_path / "d.json"],
               capsys, tmp_path / "d.json")
    assert doc["live_runs"] == [runs[2].name]


def test_session(tiny_world, tmp_path, capsys):
    """scenesig.Session's per-call latency on a demo-shaped folder of the tiny world (its night run, a few
    frames, paced at the data's clock)."""
    runs, root = tiny_world
    demo = tmp_path / "demo"
    (demo / "world").mkdir(parents=True)
    for r in runs:
        (demo / "world" / r.root.name).symlink_to(r.root)
    (demo / "map").symlink_to(root)
    (demo / "summary.json").write_text(json.dumps({"runs": [{"run": r.name} for r in runs[1:]]}))
    doc = _run("session", [demo, "--conditions", "night", "--methods", "signatures,orb", "--detector-hz", "2",
                           "--frames", "6", "--json", tmp_path / "s.json"], capsys, tmp_path / "s.json")
    night = doc["runs"][runs[2].name]
    assert night["every"] == 2 and night["image_size"] == [runs[2].camera.width, runs[2].camera.height]
    for m in ("signatures", "orb"):
        fast, paced = night[m]["unpaced"], night[m]["paced"]
        assert fast["add_image_wall_ms"]["calls"] == fast["frames"] == 6 and fast["frames_held"] == 0
        assert fast["add_image_cpu_ms"]["max"] > 0
        assert 0 < fast["add_image_wall_ms"]["p50"] <= fast["add_image_wall_ms"]["max"]
        assert paced["max_blocking_ms"] >= paced["add_image_wall_ms"]["max"]
        assert paced["within_period"] == (paced["calls_over_period"] == 0)
    assert doc["signatures_p95_ms_worst"] == night["signatures"]["unpaced"]["add_image_wall_ms"]["p95"]


# -------------------------------------------------------------------------- a few real frames
def test_kitti_import(tmp_path, capsys):
    drive = _shared("kitti", "2011_09_26_snippet")
    _run("kitti-import", [drive, "--repeats", "1", "--json", tmp_path / "k.json"], capsys, tmp_path / "k.json")


def test_kitti_drive(tmp_path, monkeypatch, capsys):
    """The snippet end to end, its map built with the tiny world's cut-down settings, ORB only."""
    drive = _shared("kitti", "2011_09_26_snippet")
    from scenesig.mapping import build

    real = build.build_map
    tiny = {**CONFIG, "places": {"spacing_m": 10.0}, "points": {**CONFIG["points"], "max_points": 50}}
    monkeypatch.setattr(build, "build_map", lambda *a, **k: real(*a, **{**k, "config": tiny, "progress": False}))
    doc = _run("kitti-drive", [drive, "--work", tmp_path / "w", "--methods", "orb", "--every", "8",
                               "--json", tmp_path / "kd.json"], capsys, tmp_path / "kd.json")
    assert "orb" in doc["replays"]["cam3"]


def _tiny_grief_season(dst: Path, frames: int = 6) -> Path:
    src = _shared("grief", "season")
    for s in ("season_00", "season_01"):
        (dst / s).mkdir(parents=True)
        for f in sorted((src / s).glob("*.jpg"))[:frames]:
            shutil.copy(f, dst / s / f.name)
    lines = (src / "season_01" / "displacements.txt").read_text().splitlines()[:frames]
    (dst / "season_01" / "displacements.txt").write_text("\n".join(lines) + "\n")
    return dst


def test_heading(tmp_path, capsys):
    data = _shared("grief", "stromovka")
    _run("heading", [data, "--methods", "orb", "--max-pairs", "2", "--json", tmp_path / "h.json"], capsys,
         tmp_path / "h.json")


def test_places(tmp_path, capsys):
    """``bench places`` on six GRIEF season frames: its arguments through ``main`` (the cheap methods), and
    the signatures method (which once failed with an AttributeError) with a cut-down template."""
    from scenesig.benchmarks import places

    data = _tiny_grief_season(tmp_path / "season")
    _run("places", [data, "--methods", "hog,vlad", "--json", tmp_path / "p.json", "--jobs", "1"], capsys,
         tmp_path / "p.json")
    doc = places.run_benchmark(data, methods=["signatures"], json_path=tmp_path / "s.json", jobs=1, progress=False,
                               config={"heading": {"mining": TINY_MINING, "augment_copies": 2}, "shortlist": 2})
    assert json.loads((tmp_path / "s.json").read_text()) and doc


def _tiny_webcam(dst: Path, per_scene: int = 8) -> Path:
    src = _shared("webcam")
    for scene in sorted(p for p in src.iterdir() if p.is_dir())[:2]:
        (dst / scene.name).mkdir(parents=True)
        for f in sorted(scene.glob("*.jpg"))[:per_scene]:
            shutil.copy(f, dst / scene.name / f.name)
    return dst


def test_webcam(tmp_path, capsys):
    data = _tiny_webcam(tmp_path / "webcam")
    _run("webcam", [data, "--methods", "orb", "--json", tmp_path / "w.json", "--exclude"], capsys, tmp_path / "w.json")


def test_webcam_speed(tmp_path, monkeypatch, capsys):
    from scenesig.benchmarks import webcam_speed

    data = _tiny_webcam(tmp_path / "webcam", per_scene=8)
    monkeypatch.setattr(webcam_speed, "N_IMAGES", 3)
    (tmp_path / "cfg.json").write_text(json.dumps({"signatures": {"mining": TINY_MINING}}))
    _run("webcam-speed", [data, "--repeat", "1", "--json", tmp_path / "ws.json", "--config", tmp_path / "cfg.json"],
         capsys, tmp_path / "ws.json")


def test_aerial(tmp_path, capsys):
    tiles = _shared("wildnav")
    _run("aerial", [tiles, "--methods", "orb", "--trials", "2", "--cache", tmp_path / "banks", "--no-progress",
                    "--json", tmp_path / "a.json"], capsys, tmp_path / "a.json")


def _integrity_layout(tmp_path, tiny_world):
    """Two 'worlds' laid out in the bench's cache from the tiny world (its three runs under the bench's run
    names, a copy of its map with firing rates), without simulating."""
    from scenesig.benchmarks.integrity import LIVE, TRAINING, Layout
    from scenesig.localiser import firing

    runs, map_dir = tiny_world
    layout = Layout(tmp_path / "cache", "tiny", 4.0)
    base_map = tmp_path / "map"
    shutil.copytree(map_dir, base_map)
    firing.for_map(base_map, runs)
    for seed in (1, 2):
        layout.runs(seed).mkdir(parents=True)
        (layout.runs(seed) / "simulate_summary.json").write_text("{}")
        for i, name in enumerate(layout.run_names()):
            (layout.runs(seed) / name).symlink_to(runs[i % len(runs)].root)
        shutil.copytree(base_map, layout.map(seed))
    assert len(layout.run_names()) == len(TRAINING) + len(LIVE)
    return layout


def test_integrity(tmp_path, capsys, tiny_world):
    """The evaluate path end to end on two 'worlds' made of the tiny world (the full path, simulation and
    build included: tests/test_integrity_sprt.py, heavy)."""
    _integrity_layout(tmp_path, tiny_world)
    doc = _run("integrity", ["--seeds", "1-2", "--evaluate", "--preset", "tiny", "--camera-hz", "4", "--cache",
                             tmp_path / "cache", "--camera-check", "--json", tmp_path / "i.json"], capsys,
               tmp_path / "i.json")
    assert [w["seed"] for w in doc["worlds"]] == [1, 2] and len(doc["worlds"][0]["runs"]) == 7
    assert {"wrong_runs_zero_accepted_rate", "wrong_run_max_accepted", "right_runs_with_alert_rate",
            "right_runs_coverage_ok_rate"} <= set(doc["summary"])
    # the camera check on each live run as calibrated, halved and doubled (5 runs x 3 scales x 2 worlds)
    cam = doc["camera_check"]
    assert len(cam["runs"]) == 30 and sum(cam["verdicts"]["correct"][k] for k in
                                          ("refused", "warned", "passed", "no_verdict")) == 10
    assert cam["verdicts"]["correct"]["refused"] == 0 and cam["verdicts"]["miscalibrated"]["refused"] > 0


@pytest.mark.heavy
def test_integrity_calibrate(tmp_path, capsys, tiny_world):
    """The calibrate path on the same two 'worlds': the tests off, every frame's statistics recorded, the
    monitor's settings and the bound model chosen (~1 min)."""
    _integrity_layout(tmp_path, tiny_world)
    doc = _run("integrity", ["--seeds", "1-2", "--calibrate", "--choose", "--preset", "tiny", "--camera-hz", "4",
                             "--cache", tmp_path / "cache", "--json", tmp_path / "c.json"], capsys, tmp_path / "c.json")
    assert {"sprt_other_factor", "cusum_h", "sprt_confirming_place"} <= set(doc["choice"]["chosen"])
    assert all((w / "integrity_stats.json").exists()
               for w in (tmp_path / "cache" / "tiny-4hz" / "seed1").glob("loc-calibrate*/run*"))
    # every wrong-map run also localised live, with the defaults, and read by the rule beside the monitor-off ones
    assert all(len(w["live_wrong_runs"]) == sum(r["kind"] == "wrong" for r in w["runs"]) == 2 for w in doc["worlds"])
    assert doc["choice"]["wrong_live_runs"] == doc["choice"]["wrong_runs"] == 4
    # the tiny map localises nothing without INS/GPS: no bound model is made up from no data (the rule on
    # synthetic runs: tests/test_integrity_sprt.py)
    assert doc["choice"]["inflation"] == {"k": None, "grid": []}


def test_every_benchmark_has_a_smoke_test():
    tested = {n[len("test_"):].replace("_", "-") for n in globals() if n.startswith("test_")}
    missing = [name for name in BENCHMARKS if name.replace("_", "-") not in tested]
    assert not missing, f"benchmarks without a smoke test in tests/test_benchmarks.py: {missing}"
    assert np.isfinite(len(BENCHMARKS))


def test_sequence(tiny_world, tmp_path, capsys):
    """``bench sequence``: two simulated runs exported as frame-aligned image folders (``--export-sim``),
    imported as ``scenesig import images`` does, scored with the cheap methods."""
    from scenesig.surveys.importers.image_folder import import_image_folder

    runs, _ = tiny_world
    a, b = runs[0], runs[-1]
    exp = _run("sequence", [a.root, b.root, "--export-sim", tmp_path / "folders", "--spacing", "6"], capsys)
    assert exp["frames"] > 5 and max(exp["max_distance_to_reference_m"].values()) < 3.0
    ref = import_image_folder(tmp_path / "folders" / a.name, tmp_path / "ref",
                              {"hz": 1, "positions": tmp_path / "folders" / f"{a.name}_positions.csv"}, progress=False)
    q = import_image_folder(tmp_path / "folders" / b.name, tmp_path / "q", {"hz": 1, "aligned_with": ref},
                            progress=False)
    doc = _run("sequence", [ref, "--query", q, "--methods", "hog,seqslam", "--json", tmp_path / "s.json"], capsys,
               tmp_path / "s.json")
    assert doc["frames"] == exp["frames"] and len(doc["matches"]["hog"]) == exp["frames"]
