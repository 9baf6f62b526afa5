"""``scenesig map show MAP [--place P] --out DIR`` (mapping/show.py) on the tiny world's map."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from build_world import tiny_map

pytest.importorskip("scenesig.surveys.sim.simulate")


@pytest.fixture(scope="module")
def map_root(tmp_path_factory):
    return tiny_map(tmp_path_factory.getbasetemp())


def _png(path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"{path} is not a readable image"
    assert img.shape[0] > 100 and img.shape[1] > 100 and img.std() > 5, f"{path} looks empty"
    return img


def test_map_show_writes_every_figure(map_root, tmp_path, capsys):
    from scenesig.cli import main

    out = tmp_path / "fig"
    assert main(["map", "show", str(map_root), "--out", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["heatmap.png", "place_0000.png", "place_0001.png", "place_0002.png", "places.png"]
    for p in out.iterdir():
        _png(p)
    printed = capsys.readouterr().out.splitlines()
    # the listing (generation, places) first, then one line per figure written
    assert printed[0].startswith(f"map {map_root}") and "generation 0" in printed[0]
    assert sum(line.startswith("place ") for line in printed) == 3
    assert sorted(Path(line).name for line in printed[-5:]) == names


def test_map_show_one_place(map_root, tmp_path, capsys):
    from scenesig.cli import main

    out = tmp_path / "one"
    assert main(["map", "show", str(map_root), "--place", "1", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["heatmap.png", "place_0001.png", "places.png"]
    # a place that is not there: a clear error naming the map, no traceback
    assert main(["map", "show", str(map_root), "--place", "7", "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert "no place 7" in err and "manifest.json" in err


def test_signature_boxes_and_depths_match_the_place(map_root):
    from scenesig.mapping.show import _boxes_and_depths
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.geometry import invert

    store = MapStore.open(map_root)
    manifest = json.loads((map_root / "manifest.json").read_text())
    for meta in manifest["places"]:
        data = store.load_place(meta["index"])
        boxes, depth = _boxes_and_depths(store, data)
        assert len(boxes) == len(depth) == data.n_signatures == meta["signatures"]
        if not len(boxes):
            continue
        # depths are the landmarks' z in the place camera
        T_cv = invert(store.T_vehicle_camera)
        np.testing.assert_allclose(depth, data.landmarks @ T_cv[2, :3] + T_cv[2, 3])
        assert np.all(depth > 0)
        # boxes are centred on the firings at the keyframe (pixel-centre coordinates + 0.5)
        centres = np.asarray(data.meta["detections_at_reference"], dtype=float)
        np.testing.assert_allclose((boxes[:, :2] + boxes[:, 2:]) / 2, centres + 0.5)
        assert np.all(boxes[:, 2] > boxes[:, 0]) and np.all(boxes[:, 3] > boxes[:, 1])


def test_map_show_rejects_a_folder_that_is_not_a_map(tmp_path, capsys):
    from scenesig.cli import main

    assert main(["map", "show", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    assert "manifest" in capsys.readouterr().err
