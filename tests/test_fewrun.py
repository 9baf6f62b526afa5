"""Maps from few survey runs (mapping.build): neighbouring frames and augmented copies give a three-run
and a one-run map signatures at every place; a map that cannot localise is never written silently --
weak places are named, and a build where no place kept a signature fails with exit 2 and advice."""
import json
import logging

import numpy as np
import pytest

pytest.importorskip("scenesig.surveys.sim.simulate")

from scenesig.cli import main as cli  # noqa: E402

TRAINING = ["sunny", "overcast", "rain"]
#: a reduced candidate template (76 shapes) and refinement window: the default code path, faster
SHAPES = {"kinds": [{"name": "square-s", "size": 0.15, "aspect": 1.0, "nx": 8, "ny": 4},
                    {"name": "wide", "size": 0.20, "aspect": 2.0, "nx": 5, "ny": 4},
                    {"name": "tall", "size": 0.20, "aspect": 0.5, "nx": 8, "ny": 3}]}
CONFIG = {"mining": {"shapes": SHAPES}, "max_window_frames": 9,
          "points": {"n_candidates": 500, "max_points": 100}, "layers": ["signatures", "orb", "orb-all"]}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The tiny world at 5 Hz: three training runs of different appearance and a held-out sunny run."""
    from scenesig.surveys.run import read_run
    from scenesig.surveys.sim.simulate import simulate

    root = tmp_path_factory.mktemp("fewrun")
    simulate(root / "runs", preset="tiny", seed=1, runs=TRAINING + ["sunny"], camera_hz=5.0, jobs=1,
             show_progress=False)
    runs = [read_run(p) for p in sorted((root / "runs").iterdir()) if p.is_dir()]
    return root, runs[:3], runs[3]


def test_three_run_map_has_signatures_everywhere_and_localises_a_day_run(world, tmp_path, caplog):
    from scenesig.localiser.replay import localise
    from scenesig.mapping.build import build_map
    from scenesig.mapping.coverage import weak_places

    root, train, live = world
    summary = build_map(train, train[0], tmp_path / "map", jobs=1, progress=False, config=CONFIG)
    per_place = summary["per_place"]
    assert len(per_place) == summary["places"] >= 5
    # three runs: two frames each (six images, two per partition), no augmentation needed
    assert all(p["runs"] == 3 and p["frames"] == 6 and p["augmented"] == 0 for p in per_place), per_place
    assert all(p["signatures"] > 0 for p in per_place), per_place
    assert summary["places_weak"] == weak_places(tmp_path / "map")
    manifest = json.loads((tmp_path / "map" / "manifest.json").read_text())
    assert [p["signatures"] for p in manifest["places"]] == [p["signatures"] for p in per_place]
    with caplog.at_level(logging.WARNING):
        m = localise(tmp_path / "map", live.root, tmp_path / "loc", every=1, progress=False, figure=False)
    assert m["failures"] == 0 and m["blind_fraction_over_20m"] == 0.0, m
    assert m["localised_fraction"] > 0.8, m
    assert m["lateral_error_map_m"]["median"] < 0.5, m
    # localise warns before replaying exactly when the route passes weak places
    warned = [r.message for r in caplog.records if "fewer than" in r.getMessage()]
    assert bool(warned) == bool(summary["places_weak"])


def test_one_run_map_builds_from_frames_and_augmented_copies(world, tmp_path, caplog):
    from build_world import SHAPES as SMALL_SHAPES

    from scenesig.mapping.build import build_map

    root, train, _ = world
    cfg = {**CONFIG, "places": {"spacing_m": 20.0}, "mining": {"shapes": SMALL_SHAPES}}
    with caplog.at_level(logging.WARNING):
        summary = build_map(train[:1], train[0], tmp_path / "one", jobs=1, progress=False, config=cfg)
    assert (tmp_path / "one" / "manifest.json").is_file()
    per_place = summary["per_place"]
    # one run: three neighbouring frames and three augmented copies per place
    assert all(p["runs"] == 1 and p["frames"] == 3 and p["augmented"] == 3 for p in per_place), per_place
    assert sum(p["signatures"] for p in per_place) > 0, per_place
    assert any("one survey run" in r.getMessage() for r in caplog.records)


def test_build_where_no_place_keeps_a_signature_exits_2_and_writes_no_map(world, tmp_path, capsys):
    root, train, _ = world
    # the paper's one frame per run and no augmentation: three images cannot fill three partitions
    cfg = {**CONFIG, "places": {"spacing_m": 20.0}, "frames_per_run": 1, "min_images": 1}
    out = tmp_path / "empty"
    code = cli(["build-map", *[str(r.root) for r in train], "--reference", str(train[0].root), "--out", str(out),
                "--config", json.dumps(cfg)])
    err = capsys.readouterr().err
    assert code == 2
    assert "no place kept a scene signature" in err and "--frames-per-run" in err and "more runs" in err
    assert "no_data" in err
    assert not (out / "manifest.json").exists() and not list((out / "places").glob("place_*"))
    summary = json.loads((out / "build_summary.json").read_text())
    assert summary["places_weak"] == list(range(summary["places"]))
    assert all(p["rejected"]["no_data"] > 0 for p in summary["per_place"])
    # nothing half-built is left to resume: a re-run with other settings starts afresh in the same folder
    assert not (out / "journal.jsonl").exists()


def _view(positions, frame):
    """A TrainingView along x (no run: only its window geometry is used)."""
    from scenesig.mapping.places import TrainingView
    from scenesig.surveys.geometry import make_pose

    window = np.arange(len(positions))
    T = np.stack([make_pose(np.eye(3), [x - positions[frame], 0.0, 0.0]) for x in positions])
    return TrainingView(None, frame, window, T, 0.0)


def test_neighbour_frames_alternate_ahead_and_behind_within_the_segment():
    from scenesig.mapping.places import neighbour_frames

    v = _view(np.arange(0.0, 10.01, 0.5), frame=10)          # 0.5 m apart, training frame at 5 m
    assert neighbour_frames(v, 1, 1.0, 5.0).tolist() == [10]
    assert neighbour_frames(v, 3, 1.0, 5.0).tolist() == [10, 12, 8]
    assert neighbour_frames(v, 5, 2.0, 5.0).tolist() == [10, 14, 6, 18, 2]
    # never beyond the segment, so at most 1 + 2 * 2 frames 2 m apart within 5 m
    assert len(neighbour_frames(v, 9, 2.0, 5.0)) == 5
    # at the start of a run only frames ahead exist
    assert neighbour_frames(_view(np.arange(0.0, 10.01, 0.5), frame=0), 3, 1.0, 5.0).tolist() == [0, 2, 4]
    # stopped for ten frames: frames at the same spot are no new viewpoints, the next ones ahead are taken
    stop = np.r_[np.zeros(10), np.arange(0.5, 5.01, 0.5)]
    assert neighbour_frames(_view(stop, frame=5), 3, 1.0, 5.0).tolist() == [5, 11, 13]


def test_six_runs_mine_exactly_the_papers_training_images():
    """Six runs or more: one frame per run, no augmentation -- such maps are built as before."""
    from scenesig.mapping.build import _merge
    from scenesig.mapping.selection import frames_per_run, mining_images

    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (24, 32), dtype=np.uint8) for _ in range(6)]
    views = [_view(np.arange(0.0, 10.01, 0.5), frame=10) for _ in range(6)]
    out, offsets, counts = mining_images(0, views, images, _merge(None))
    assert len(out) == 6 and all(a is b for a, b in zip(out, images))
    assert not offsets.any() and counts == {"frames_per_run": 1, "frames": 6, "augmented": 0}
    cfg = _merge(None)
    assert [frames_per_run(cfg, n) for n in (1, 2, 3, 4, 5, 6, 12)] == [3, 3, 2, 2, 2, 1, 1]
    # one run, one frame each: augmented copies fill the place up to min_images, shifted as they report
    out, offsets, counts = mining_images(0, views[:1], images[:1], _merge({"frames_per_run": 1}))
    assert counts == {"frames_per_run": 1, "frames": 1, "augmented": 5} and len(out) == 6
    assert all(o.shape == images[0].shape and o.dtype == np.uint8 for o in out)
    assert offsets[0].tolist() == [0.0, 0.0] and np.all(np.abs(offsets[1:, 0]) <= 8.0) and not offsets[:, 1].any()
