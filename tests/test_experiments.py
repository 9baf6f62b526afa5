"""The paper's experiments (scenesig/experiments.py, scenesig/plots.py): matching within δ, heat maps,
localisation figures."""
import json

import numpy as np
import pytest
from point_world import CAMERA, T_VC, camera_pose, planes, render, vehicle_pose

from scenesig.experiments import (
    aligned_frame,
    dead_reckoning,
    find_localise_outputs,
    frame_distances,
    matching_experiment,
    read_localise_output,
    signature_matches,
)
from scenesig.mapping.pointmap import triangulate_keyframe
from scenesig.mapping.store import MapStore, MapWriter, PlaceData
from scenesig.plots import localisation_figures, write_matching
from scenesig.signatures.bank import Bank, Classifier
from scenesig.signatures.hog import default_config as hog_default, fhog
from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import make_pose, rot_z
from scenesig.surveys.run import SurveyRun, read_run, write_run

T_WORLD_ROAD = make_pose(rot_z(0.3), [100.0, 50.0, 0.0])   # the road's frame in the world
PLACE_X = (0.0, 10.0)


def template_bank(image, boxes):
    """Classifiers whose filters are the HOG of patches of ``image`` (they fire where the patch is)."""
    f = fhog(image)
    cls = []
    for x, y, w, h in boxes:
        c0, r0, cw, ch = x // 8, y // 8, w // 8, h // 8
        wts = f[r0:r0 + ch, c0:c0 + cw] - f[r0:r0 + ch, c0:c0 + cw].mean()
        cls.append(Classifier(weights=wts, bias=0.0, level=0, box=(x, y, w, h), nominal_xy=(x + w / 2, y + h / 2),
                              nominal_scale=1.0, calibration=(1.0, 0.0), hog=dict(hog_default)))
    return Bank(cls, image_size=(image.shape[1], image.shape[0]))


def make_run(folder, world, xs, name, conditions):
    poses = np.stack([T_WORLD_ROAD @ vehicle_pose(x) for x in xs])
    t = np.arange(len(xs)) * 0.1
    run = SurveyRun(name=name, conditions=conditions, camera=CAMERA, T_vehicle_camera=T_VC,
                    rates={"camera_hz": 10.0, "odometry_hz": 10.0, "ins_hz": 10.0}, frame_times=t, frame_files=[],
                    odometry_times=t, odometry_poses=poses, groundtruth_times=t, groundtruth_poses=poses,
                    truth_times=t, truth_poses=poses, metadata={})
    write_run(run, folder, images=[render(camera_pose(vehicle_pose(x)), world)[0] for x in xs])
    return read_run(folder)


@pytest.fixture(scope="module")
def matching_setup(tmp_path_factory):
    base = tmp_path_factory.mktemp("matching")
    world = planes(seed=0)
    w = MapWriter(base / "map", CAMERA, T_VC, {})
    metas = []
    boxes = [(16, 40, 48, 48), (232, 48, 48, 48), (136, 88, 32, 32), (40, 96, 40, 40)]
    for i, x0 in enumerate(PLACE_X):
        key, _ = render(camera_pose(vehicle_pose(x0)), world)
        imgs = [render(camera_pose(vehicle_pose(x0 + b)), world)[0] for b in (-5.0, -2.5, 2.5, 5.0)]
        pts, _ = triangulate_keyframe(key, imgs, np.stack([vehicle_pose(b) for b in (-5.0, -2.5, 2.5, 5.0)]),
                                      CAMERA, T_VC)
        bank = template_bank(key, boxes)
        d = bank.detect(key, top_n=1)
        ref = np.column_stack([d.x[:, 0], d.y[:, 0]])
        n = len(bank)
        w.write_place(i, PlaceData(bank.to_arrays(), np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)),
                                   np.arange(n), keyframe=key, points=pts,
                                   meta={"detections_at_reference": ref.tolist()}))
        metas.append({"index": i, "T_world_place": T_WORLD_ROAD @ vehicle_pose(x0), "neighbours": [1 - i]})
    w.finalise(metas)
    store = MapStore.open(base / "map")
    # a run through the same street 0.3 m off the map's poses, and one through another street
    same = make_run(base / "same", world, [-0.3, 0.3, 9.8, 30.0], "same", ["sunny"])
    other = make_run(base / "other", planes(seed=7), [0.1, 10.2], "other", ["elsewhere"])
    return base, store, same, other, boxes


def test_aligned_frame_is_nearest_by_truth_and_gated(matching_setup):
    _, store, same, other, _ = matching_setup
    assert aligned_frame(same, store.places[0].T_world_place) in (0, 1)
    assert aligned_frame(same, store.places[1].T_world_place) == 2
    far = T_WORLD_ROAD @ vehicle_pose(60.0)
    assert aligned_frame(same, far, max_distance_m=5.0) is None
    backwards = T_WORLD_ROAD @ vehicle_pose(10.0, yaw=np.pi)
    assert aligned_frame(same, backwards) is None


def test_signature_matches_count_within_delta(matching_setup):
    _, store, same, _, boxes = matching_setup
    data = store.load_place(0)
    bank = Bank.from_arrays(data.bank_arrays)
    ref = np.asarray(data.meta["detections_at_reference"])
    key = data.keyframe_image()
    assert key is not None
    img = same.image(0)
    matched, live_boxes = signature_matches(bank, ref, img, 15.0)
    assert matched.sum() >= 3 and len(live_boxes) == matched.sum()
    # shift the map positions by 20 px: nothing agrees within 15 px any more
    matched, _ = signature_matches(bank, ref + [20.0, 0.0], img, 15.0)
    assert matched.sum() == 0


def test_matching_experiment_counts_and_heat_maps(matching_setup):
    base, store, same, other, boxes = matching_setup
    res = matching_experiment(store, [same, other], progress=False)
    assert res.methods == ["signatures", "orb", "sift"]
    assert res.frames.shape == (2, 2) and (res.frames >= 0).all()
    for m in ("orb", "sift"):
        assert np.all(res.counts[m][0] >= 20), (m, res.counts[m])        # the same street: many agree
        # another street (same wall geometry, other textures): only the walls' outline corners agree
        assert np.all(res.counts[m][1] < 0.1 * res.counts[m][0]), (m, res.counts[m])
        assert np.all(res.putative[m][0] >= res.counts[m][0])
    assert np.all(res.counts["signatures"][0] >= 3)
    # heat of the signatures lies inside the classifiers' boxes (+1 per pixel, mean over the 2 runs)
    sc = 0.25
    h = res.heat["signatures"][0]
    inside = np.zeros_like(h, bool)
    for x, y, w, hh in boxes:
        inside[int((y - 16) * sc):int((y + hh + 16) * sc), int((x - 16) * sc):int((x + w + 16) * sc)] = True
    assert h.sum() > 0 and h[~inside].sum() < 0.05 * h.sum()
    paths = write_matching(res, store, base / "out")
    for p in paths.values():
        assert p.is_file() and p.stat().st_size > 1000
    doc = json.loads(paths["json"].read_text())
    assert doc["summary"]["orb"]["same"]["places_with_match"] == 1.0
    assert doc["summary"]["orb"]["other"]["matches_mean"] < 0.1 * doc["summary"]["orb"]["same"]["matches_mean"]


# ------------------------------------------------------------------------------------ localisation
@pytest.fixture(scope="module")
def localise_outputs(tmp_path_factory):
    from pipeline_world import NothingMethod, TruthMethod, make_live_run, make_map

    from scenesig.localiser.replay import replay, write_outputs

    base = tmp_path_factory.mktemp("localised")
    store = make_map(base / "map")
    run = make_live_run(base / "runs" / "live", length_m=100.0)
    methods = {"signatures": TruthMethod(run), "orb": TruthMethod(run, blind=[(20.0, 70.0)]), "sift": NothingMethod()}
    metrics = {}
    for name, m in methods.items():
        m.name = name
        res = replay(store, run, m, every=4)
        metrics[name] = write_outputs(res, store, base / "demo" / "live" / name, figure=False)
    return base, run, metrics


def test_localisation_outputs_round_trip_and_dead_reckoning(localise_outputs):
    base, run, metrics = localise_outputs
    folders = find_localise_outputs([base / "demo"])
    assert len(folders) == 3
    outs = [read_localise_output(f) for f in folders]
    by = {o.method: o for o in outs}
    d = np.linspace(0, 60, 61)
    curves = dead_reckoning(outs, d, {"live": run})
    # Fig. 25 at 20 m is the metric blind_fraction_over_20m; a method that never localises is blind
    # beyond d everywhere past the first d metres from its known start: P(d) = 1 - d / L
    for m in ("signatures", "orb", "sift"):
        assert np.isclose(curves[m]["p"][20], metrics[m]["blind_fraction_over_20m"], atol=1e-6)
    length = frame_distances(by["sift"], run)[-1]
    assert np.allclose(curves["sift"]["p"], 1.0 - d / length, atol=0.02)
    assert curves["orb"]["p"][20] > 0.2 and curves["signatures"]["p"][20] == 0.0
    assert np.all(np.diff(curves["orb"]["p"]) <= 1e-12)
    # without the run, distances come from the estimate, close to the truth's
    s_truth = frame_distances(by["signatures"], run)
    s_est = frame_distances(by["signatures"])
    assert abs(s_est[-1] - s_truth[-1]) < 0.03 * s_truth[-1]
    figs = localisation_figures(outs, base / "figs", {"live": run})
    assert figs["runs"]["live"].is_file() and figs["dead_reckoning"].is_file()


def test_read_localise_output_errors(localise_outputs, tmp_path):
    import shutil

    base = localise_outputs[0]
    bad = tmp_path / "bad"
    shutil.copytree(base / "demo" / "live" / "orb", bad)
    lines = (bad / "frames.csv").read_text().splitlines()
    lines[3] = lines[3].replace(",", ",x", 1)
    (bad / "frames.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"frames.csv:4: ") as e:
        read_localise_output(bad)
    assert "not a number" in str(e.value)
    (bad / "metrics.json").unlink()
    with pytest.raises(DataError, match="metrics.json"):
        read_localise_output(bad)
