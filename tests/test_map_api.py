"""The map's front door (``scenesig.Map.open``) and the typed build summary (``BuildSummary``) on the tiny
world's map: what they report is what the map folder holds."""
import json

import pytest

import scenesig
from scenesig.mapping.build_summary import BuildSummary
from scenesig.surveys.errors import DataError


def test_map_open_reports_the_folder(tiny_world):
    _, root = tiny_world
    m = scenesig.Map.open(root)
    manifest = json.loads((root / "manifest.json").read_text())
    assert len(m) == len(m.places) == len(manifest["places"]) >= 2
    assert m.layers == ["signatures", "orb", "orb-all"]          # tests/build_world.py's CONFIG
    assert m.identity == (manifest["map_id"], 0) and m.map_id == manifest["map_id"] and m.generation == 0
    assert m.settings == manifest["params"]["settings"] and m.settings["places"]["spacing_m"] == 20.0
    assert [p.index for p in m.places.values()] == [p["index"] for p in manifest["places"]]
    assert m.load_place(min(m.places)).bank_arrays
    i = min(m.places)
    assert m.nearest_place(m.places[i].T_world_place) == i
    assert "Map(" in repr(m) and str(root) in repr(m)


def test_map_summary_is_the_build_summary_typed(tiny_world):
    _, root = tiny_world
    doc = json.loads((root / "build_summary.json").read_text())
    s = scenesig.Map.open(root).summary
    assert isinstance(s, BuildSummary)
    assert dict(s) == doc and s.to_dict() == doc and list(s) == list(doc)      # exactly the file, in order
    assert s.places == doc["places"] == s["places"] and s.layers == doc["layers"]
    assert s.places_weak == doc["places_weak"] and s.signatures_per_place_mean == doc["signatures_per_place_mean"]
    assert s.get("no such key") is None and "per_place" in s


def test_build_summary_keeps_unknown_keys_and_fills_missing_ones():
    s = BuildSummary.from_dict({"places": 3, "signatures_per_place_mean": 12.5, "added_later": [1]})
    assert s.places == 3 and s.layers is None and s["added_later"] == [1] and len(s) == 3
    assert s == {"places": 3, "signatures_per_place_mean": 12.5, "added_later": [1]}


def test_bad_map_folders_name_the_file(tmp_path):
    with pytest.raises(DataError, match="manifest.json"):
        scenesig.Map.open(tmp_path)
    with pytest.raises(DataError, match="build_summary.json.*no build summary"):
        BuildSummary.read(tmp_path)
    (tmp_path / "build_summary.json").write_text("{not json")
    with pytest.raises(DataError, match="build_summary.json.*not valid JSON"):
        BuildSummary.read(tmp_path)
    (tmp_path / "build_summary.json").write_text("[]")
    with pytest.raises(DataError, match="not a build summary"):
        BuildSummary.read(tmp_path)
