"""Map layers (mapping.layers): names, what a method needs, what a map holds, and the localiser's refusal."""
import numpy as np
import pytest
from point_world import CAMERA, T_VC

from scenesig.cli import main
from scenesig.mapping import layers
from scenesig.mapping.store import MapStore, MapWriter, PlaceData
from scenesig.surveys.errors import DataError


def test_parse_layers_adds_signatures_orders_and_rejects_unknown():
    assert layers.parse_layers(None) == ["signatures"] == list(layers.DEFAULT_LAYERS)
    assert layers.parse_layers("sift-all, orb") == ["signatures", "orb", "sift-all"]
    assert layers.parse_layers(["xfeat", "signatures"]) == ["signatures", "xfeat"]
    assert layers.parse_layers("all") == list(layers.LAYERS)
    with pytest.raises(ValueError, match="unknown map layer.*surf"):
        layers.parse_layers("orb,surf")


def test_method_layers_and_point_plan():
    assert layers.method_layers("signatures-none") == ("signatures",)
    assert layers.method_layers("xfeat-all") == ("xfeat-all",)
    with pytest.raises(ValueError):
        layers.method_layers("bogus")
    plan = layers.point_plan(["orb", "sift-all", "xfeat"])
    assert plan == {"reference": ["orb", "xfeat"], "all": ["sift"], "extract": ["orb", "sift", "xfeat"]}


def test_map_layers_of_old_and_new_manifests():
    # a map built before layers: the build settings it records (ORB and SIFT, both point maps, by default)
    assert layers.map_layers({"config": {}}) == ["signatures", "orb", "sift", "orb-all", "sift-all"]
    assert layers.map_layers({"config": {"points": {"kinds": ["orb"]}, "point_maps": ["reference"]}}) == \
        ["signatures", "orb"]
    assert layers.map_layers({"config": {"layers": ["signatures", "xfeat-all"]}}) == ["signatures", "xfeat-all"]
    assert layers.layer_of_member("points/orb_all_desc.npy") == "orb-all"
    assert layers.layer_of_member("points/xfeat_kp.npy") == "xfeat"
    assert layers.layer_of_member("points/all_T_place_keyframe.npy") == "all_keyframe_poses"
    assert layers.layer_of_member("bank/weights.npy") == "signatures"
    assert layers.layer_of_member("meta.npy") == "meta"


def _store(root, points):
    empty = dict(bank_arrays={}, landmarks=np.zeros((0, 3)), covariances=np.zeros((0, 3, 3)),
                 classifier_ids=np.zeros(0, int))
    w = MapWriter(root, CAMERA, T_VC, {"config": {"layers": ["signatures", "orb"]}})
    w.write_place(0, PlaceData(**empty, points=points))
    w.finalise([{"index": 0, "T_world_place": np.eye(4), "neighbours": []}])
    return MapStore.open(root)


def test_localise_refuses_a_method_whose_layer_the_map_lacks(tmp_path):
    from scenesig.localiser.replay import _check_layers

    pts = {"orb_kp": np.zeros((3, 2), np.float32), "orb_desc": np.zeros((3, 32), np.uint8),
           "orb_xyz": np.ones((3, 3), np.float32), "orb_sigma": np.ones((3, 2), np.float16)}
    store = _store(tmp_path / "m", pts)
    assert layers.store_layers(store) == ["signatures", "orb"]
    _check_layers(store, "orb")
    _check_layers(store, "signatures")
    with pytest.raises(DataError, match=r"'sift-all' needs the map layer sift-all.*build-map --layers "
                                        r"signatures,orb,sift-all"):
        _check_layers(store, "sift-all")


def test_cli_refuses_a_missing_layer_and_bad_layer_names(tmp_path, capsys):
    from conftest import make_run

    from scenesig.surveys.run import write_run

    store = _store(tmp_path / "m", {})
    run, images = make_run(n_frames=4, size=(CAMERA.width, CAMERA.height))
    write_run(run, tmp_path / "run", images)
    assert main(["localise", str(store.root), str(tmp_path / "run"), "--method", "xfeat",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "needs the map layer xfeat" in err and "manifest.json" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    assert main(["build-map", str(tmp_path / "run"), "--reference", str(tmp_path / "run"), "--out",
                 str(tmp_path / "m2"), "--layers", "orb,nope"]) == 2
    assert "unknown map layer(s) nope" in capsys.readouterr().err


def test_build_with_an_xfeat_layer_and_no_model_stops_before_writing(tmp_path, monkeypatch):
    from conftest import make_run

    from scenesig.mapping.build import build_map
    from scenesig.signatures.xfeat import ModelNotFoundError

    run, _ = make_run(n_frames=4)
    monkeypatch.setenv("SCENESIG_XFEAT_MODEL", str(tmp_path / "absent.onnx"))
    with pytest.raises(ModelNotFoundError, match="absent.onnx"):
        build_map([run], run, tmp_path / "m", progress=False, config={"layers": ["signatures", "xfeat"]})
    assert not (tmp_path / "m").exists()


def test_add_layers_refuses_all_run_layers_and_unknown_names(tmp_path, capsys):
    store = _store(tmp_path / "m", {})
    for layers_arg, msg in (("sift-all", "need every training run"), ("bogus", "unknown map layer"),
                            ("signatures", "no point-feature layer")):
        assert main(["map", "add-layers", str(store.root), "--reference", str(tmp_path / "run"),
                     "--layers", layers_arg]) == 2
        assert msg in capsys.readouterr().err
