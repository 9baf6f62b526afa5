"""Maps from few survey runs (mapping.build): neighbouring frames and augmented copies give a three-run
and a one-run map signatures at every place; a map that cannot localise is never written silently --
weak places are named, and a build where no place kept a signature fails with exit 2 and advice."""
import json
import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("surveys.sim.simulate")

from localiser.cli import main as cli  # noqa: E402

TRAINING = ["sunny", "overcast", "rain"]
#: a reduced candidate template (76 shapes) and refinement window: the default code path, faster
SHAPES = {"kinds": [{"name": "square-s", "size": 0.15, "aspect": 1.0, "nx": 8, "ny": 4},
                    {"name": "wide", "size": 0.20, "aspect": 2.0, "nx": 5, "ny": 4},
                    {"name": "tall", "size": 0.20, "aspect": 0.5, "nx": 8, "ny": 3}]}
CONFIG = {"mining": {"shapes": SHAPES}, "max_window_frames": 9,
          "points": {"kinds": ["orb"], "n_candidates": 500, "max_points": 100}}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The tiny world at 5 Hz: three training runs of different appearance and a held-out sunny run."""
    from surveys.run import read_run
    from surveys.sim.simulate import simulate

    root = tmp_path_factory.mktemp("fewrun")
    simulate(root / "runs", preset="tiny", seed=1, runs=TRAINING + ["sunny"], camera_hz=5.0, jobs=2,
             show_progress=False)
    runs = [read_run(p) for p in sorted((root / "runs").iterdir()) if p.is_dir()]
    return root, runs[:3], runs[3]


def test_three_run_map_has_signatures_everywhere_and_localises_a_day_run(world, tmp_path, caplog):
    from localiser.replay import localise
    from mapping.build import build_map
    from mapping.coverage import weak_places

    root, train, live = world
    summary = build_map(train, train[0], tmp_path / "map", jobs=2, progress=False, config=CONFIG)
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
    from mapping.build import build_map

    root, train, _ = world
    cfg = {**CONFIG, "places": {"spacing_m": 20.0}}
    with caplog.at_level(logging.WARNING):
        summary = build_map(train[:1], train[0], tmp_path / "one", jobs=2, progress=False, config=cfg)
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
    # a re-run with more frames per run starts afresh in the same folder
    cfg.pop("frames_per_run"), cfg.pop("min_images")
    assert cli(["build-map", *[str(r.root) for r in train], "--reference", str(train[0].root), "--out", str(out),
                "--config", json.dumps(cfg)]) == 0
    assert (out / "manifest.json").is_file()
