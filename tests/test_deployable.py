"""A deployable localiser: it runs without ground truth (evaluation is a step of its own), states every
frame's uncertainty (95 % bounds from the pose graph's marginals, ``covariances.csv``), and a map update
only takes localisations of the map (and generation) it updates."""
import dataclasses
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from pipeline_world import TruthMethod, make_live_run, make_map

from scenesig.cli import main
from scenesig.localiser.outputs import TRUTH_KEYS, read_frames_csv, write_outputs
from scenesig.localiser.replay import replay

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("deployable_world")
    run = make_live_run(root / "live", length_m=60.0)
    store = make_map(root / "map", length_m=80.0)
    return root, run, store


def _no_truth(run):
    return dataclasses.replace(run, truth_times=None, truth_poses=None, groundtruth_times=None,
                               groundtruth_poses=None)


def _finite_json(obj) -> bool:
    text = json.dumps(obj, allow_nan=False)    # raises on NaN / inf
    return "NaN" not in text


# ------------------------------------------------------------------------------------- 1. no truth needed
def test_outputs_without_truth_and_the_same_trajectory(world, tmp_path):
    """Without truth: every output written, ``truth_source: "none"``, no error keys; trajectory and
    covariances byte-identical to the same replay written with truth; ``scenesig evaluate`` later gives
    the errors the in-process evaluation gives."""
    _, run, store = world
    res = replay(store, run, TruthMethod(run), every=4)
    with_truth = write_outputs(res, store, tmp_path / "truth", figure=False)
    blind = dataclasses.replace(res, run=_no_truth(run))
    m = write_outputs(blind, store, tmp_path / "none", figure=True)
    out = tmp_path / "none"
    assert sorted(p.name for p in out.iterdir()) == ["covariances.csv", "frames.csv", "metrics.json",
                                                     "trajectory.png", "trajectory.tum"]
    for name in ("trajectory.tum", "covariances.csv"):
        assert (out / name).read_bytes() == (tmp_path / "truth" / name).read_bytes(), name
    disk = json.loads((out / "metrics.json").read_text())
    assert disk["truth_source"] == "none" and with_truth["truth_source"] == "truth"
    assert not set(TRUTH_KEYS) & set(disk), "no error keys without truth"
    assert _finite_json(disk) and disk == m
    # what needs no truth is there: coverage along the odometry, the bounds, the map's identity
    assert disk["localised_fraction"] == pytest.approx(1.0) and disk["failures"] == 0
    assert disk["distance_m"] == pytest.approx(with_truth["distance_m"], rel=0.05)
    assert disk["lateral_bound_95_m_median"] == with_truth["lateral_bound_95_m_median"] > 0
    assert disk["map_id"] == store.map_id and disk["map_generation"] == 0
    fr_none, fr_truth = read_frames_csv(out / "frames.csv"), read_frames_csv(tmp_path / "truth" / "frames.csv")
    assert np.isnan(fr_none["lateral_error"]).all() and np.isfinite(fr_truth["lateral_error"]).all()
    for c in ("lateral_bound_95_m", "longitudinal_bound_95_m", "heading_bound_95_deg", "localised", "place"):
        np.testing.assert_array_equal(fr_none[c], fr_truth[c])

    # evaluation on its own, from the files, with the truth given separately
    truth_file = Path(run.root) / "truth.tum"
    assert main(["evaluate", str(out), "--truth", str(truth_file), "--no-figure"]) == 0
    ev = json.loads((out / "metrics.json").read_text())
    assert ev["truth_source"] == "truth"
    for k in ("lateral_error_m", "heading_error_deg", "localised_fraction", "bound_coverage_95",
              "bound_coverage_95_all", "false_fixes", "frames_evaluated"):
        assert ev[k] == pytest.approx(with_truth[k], rel=1e-6, abs=1e-9), k
    fr = read_frames_csv(out / "frames.csv")
    np.testing.assert_allclose(fr["lateral_error"], fr_truth["lateral_error"], atol=2e-6)
    # ... and without truth anywhere, evaluate says so and changes nothing
    before = (out / "metrics.json").read_bytes()
    assert main(["evaluate", str(out), "--truth", str(tmp_path / "missing.tum")]) == 2
    assert (out / "metrics.json").read_bytes() == before


def test_report_and_figures_take_outputs_without_truth(world, tmp_path):
    from scenesig.report import build_report

    _, run, store = world
    res = replay(store, run, TruthMethod(run), every=4)
    write_outputs(dataclasses.replace(res, run=_no_truth(run)), store, tmp_path / "loc" / "live" / "signatures")
    index = build_report([tmp_path / "loc"], tmp_path / "report")
    assert Path(index).is_file() and "lateral bound 95 %" in Path(index).read_text()
    assert main(["experiment", "localisation", str(tmp_path / "loc"), "--out", str(tmp_path / "fig")]) == 0


def test_oracle_ins_without_ins_fails_before_replaying(world, tmp_path, capsys):
    _, run, store = world
    bare = tmp_path / "bare"
    shutil.copytree(run.root, bare)
    for name in ("groundtruth.tum", "gps.csv"):
        (bare / name).unlink(missing_ok=True)
    assert main(["localise", str(store.root), str(bare), "--oracle", "ins", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "groundtruth.tum" in err and "localise" not in err.split("error:")[0]
    assert "it/s" not in err and "frame/s" not in err          # no progress bar: nothing was replayed
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------- 2. uncertainty out
def test_bounds_from_the_marginals_are_honest_and_beside_the_trajectory(world, tmp_path):
    """A weak localiser whose noise is what its covariance says: the bounds cover about 95 % of the
    lateral errors (relative to the map: it has its own georeferencing error here), both for the localised
    frames and for every frame; ``covariances.csv`` holds what the bounds come from."""
    from evo.tools import file_interface

    from scenesig.localiser.evaluation import ReferencePath
    from scenesig.localiser.uncertainty import INFLATION, Z_95, read_covariances_csv
    from scenesig.surveys.geometry import make_pose, rot_z

    root, run, _ = world
    T_off = make_pose(rot_z(0.01), [3.0, -2.0, 0.0])
    store = make_map(tmp_path / "misplaced", length_m=80.0, T_map_world=T_off)
    sigma = (0.003, 0.003, 0.01, 0.25, 0.25, 0.1)
    res = replay(store, run, TruthMethod(run, sigma=sigma, T_map_world=T_off), every=2)
    m = write_outputs(res, store, tmp_path / "out", figure=False)
    fr = read_frames_csv(tmp_path / "out" / "frames.csv")
    lat, bound = np.abs(fr["lateral_error"]), fr["lateral_bound_95_m"]
    assert np.isfinite(bound).all() and np.all(bound > 0)
    assert m["bound_coverage_95"] >= 0.9 and m["bound_coverage_95_all"] >= 0.9, m
    loc = fr["localised"] > 0
    m_lat = _map_relative(res, store)
    assert m["bound_coverage_95"] == pytest.approx(np.mean(np.abs(m_lat[loc]) <= bound[loc]))
    assert np.mean(lat <= bound) < 0.5, "the raw errors carry the map's 3.6 m offset: not covered"
    # the raw marginal (before the calibrated inflation) is near the weak localiser's own sigma
    raw = m["lateral_bound_95_m_median"] / INFLATION
    assert Z_95 * 0.25 * 0.3 < raw < 2.0 * Z_95 * 0.25
    assert m["lateral_bound_95_m_median"] == pytest.approx(np.median(bound[loc]))
    # covariances.csv: one planar covariance per pose of the trajectory (which evo still reads)
    t, P = read_covariances_csv(tmp_path / "out" / "covariances.csv")
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "out" / "trajectory.tum"))
    np.testing.assert_allclose(t, traj.timestamps, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    _, left, _ = ReferencePath(np.stack([store.places[i].T_world_place for i in sorted(store.places)])).project(
        res.poses[:, :3, 3])
    lat_sigma = np.sqrt(np.einsum("ni,nij,nj->n", left, P[:, :2, :2], left))
    np.testing.assert_allclose(Z_95 * lat_sigma, bound, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.degrees(Z_95 * np.sqrt(P[:, 2, 2])), fr["heading_bound_95_deg"], rtol=1e-5)


def _map_relative(res, store):
    from scenesig.localiser.evaluation import lateral_heading_errors
    from scenesig.localiser.outputs import map_relative_truth, reference_path
    from scenesig.surveys.geometry import interpolate_poses

    run = res.run
    tm = interpolate_poses(run.truth_times, map_relative_truth(store, run.truth_poses), res.times).reshape(-1, 4, 4)
    return lateral_heading_errors(res.poses, tm, reference_path(store))[0]


def test_bounds_grow_while_dead_reckoning(world):
    """Blind stretches: the marginal (and so the bound) grows with the odometry since the last fix; the
    innovation term, held from the last fixes through the stretch, only adds to it."""
    from pipeline_world import SPEED

    from scenesig.localiser.uncertainty import bounds_from_result

    _, run, store = world
    marginal = replay(store, run, TruthMethod(run, blind=[(20.0, 38.0)]), every=2,
                      config={"localiser": {"innovation_factor": 0.0}})
    stated = replay(store, run, TruthMethod(run, blind=[(20.0, 38.0)]), every=2)
    b0 = bounds_from_result(marginal, store)["lateral_bound_95_m"]
    b = bounds_from_result(stated, store)["lateral_bound_95_m"]
    s = 2.0 + SPEED * (marginal.times - run.truth_times[0])
    inside, before = (s > 21) & (s < 37), s < 18
    assert np.median(b0[inside]) > 1.5 * np.median(b0[before])
    for bound in (b0, b):
        assert np.all(np.diff(bound[inside]) >= -1e-9), "no fix in the stretch: the bound only grows"
    ok = np.isfinite(b0)
    assert np.all(b[ok] >= b0[ok] - 1e-9)


def test_stated_covariance_adds_the_recent_innovations(world):
    """The stated covariance is the marginal plus ``(f · ē)²`` on x and y, ``ē`` the mean planar innovation of
    the last localisations (localiser.uncertainty.innovation_variance): fixes that keep disagreeing with the
    prediction widen the bound; ``innovation_factor`` 0 leaves the marginal alone."""
    from scenesig.localiser.uncertainty import INNOVATION_FACTOR, innovation_variance

    assert innovation_variance([0.2, 0.4, np.nan], 0.15) == pytest.approx((0.15 * 0.3) ** 2)
    assert innovation_variance([], 0.15) == 0.0
    _, run, store = world
    noisy = (0.003, 0.003, 0.01, 0.4, 0.4, 0.1)
    plain = replay(store, run, TruthMethod(run, sigma=noisy), every=2, config={"localiser": {"innovation_factor": 0.0}})
    added = replay(store, run, TruthMethod(run, sigma=noisy), every=2)
    assert added.settings["localiser"]["innovation_factor"] == INNOVATION_FACTOR > 0
    np.testing.assert_allclose(added.poses, plain.poses, atol=1e-9)     # the estimate is not touched
    ok = np.isfinite(plain.covariances).all(axis=(1, 2)) & (plain.localised > 0)
    extra = added.covariances[ok] - plain.covariances[ok]
    np.testing.assert_allclose(extra[:, 3, 3], extra[:, 4, 4])           # isotropic in the plane
    others = extra.copy()
    others[:, 3, 3] = others[:, 4, 4] = 0.0
    np.testing.assert_allclose(others, 0.0, atol=1e-12)
    # noise of 0.4 m per axis: planar innovations of about half a metre, so (f · 0.5 m)² give or take
    assert (INNOVATION_FACTOR * 0.2) ** 2 < np.median(extra[:, 3, 3]) < (INNOVATION_FACTOR * 1.2) ** 2


def test_posegraph_covariance_at_a_time_matches_the_latest_and_grows_with_odometry():
    import tempfile

    from scenesig.localiser.pipeline import Localiser

    with tempfile.TemporaryDirectory() as d:
        run = make_live_run(Path(d) / "live", length_m=30.0)
        store = make_map(Path(d) / "map", length_m=40.0)
        loc = Localiser(store, lambda t: run.pose_at(t, "groundtruth"))
        incs = run.odometry_increments()
        loc.start(float(run.odometry_times[0]))
        for k in range(1, 30):
            loc.add_odometry(float(run.odometry_times[k]), incs[k - 1])
        t_last = float(run.odometry_times[29])
        np.testing.assert_allclose(loc.covariance(t_last), loc.graph.covariance(), rtol=1e-9, atol=1e-15)
        earlier = loc.covariance(float(run.odometry_times[20]))
        assert np.trace(earlier[3:, 3:]) < np.trace(loc.covariance(t_last)[3:, 3:])


# ------------------------------------------------------------------------------------- 5. map identity
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny map and its night run's localisation (shared with tests/test_update.py)."""
    from build_world import tiny_map, tiny_runs

    from scenesig.localiser.replay import localise

    base = tmp_path_factory.getbasetemp()
    runs = tiny_runs(base)
    root = tiny_map(base)
    night = next(r for r in runs if r.conditions[0] == "night")
    loc = base / "loc_night"
    if not (loc / "metrics.json").exists():
        localise(root, night.root, loc, progress=False, figure=False)
    return root, loc, night


def _tree_hash(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(Path(root).rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def _other_map(root: Path, dst: Path) -> Path:
    """Another map of the same runs and settings: what a second build gives, but for its identity."""
    from scenesig.mapping.identity import new_map_id

    shutil.copytree(root, dst)
    doc = json.loads((dst / "manifest.json").read_text())
    doc["map_id"] = new_map_id()
    (dst / "manifest.json").write_text(json.dumps(doc, indent=1, sort_keys=True))
    return dst


def test_localisation_records_the_map_identity(tiny):
    from scenesig.mapping.store import MapStore

    root, loc, _ = tiny
    m = json.loads((loc / "metrics.json").read_text())
    store = MapStore.open(root)
    assert m["map_id"] == store.map_id and m["map_generation"] == store.generation == 0
    assert len(store.map_id) == 36 and not store.map_id_derived


def test_map_update_refuses_another_maps_localisation_and_out_onto_another_map(tiny, tmp_path, capsys):
    root, loc, _ = tiny
    other = _other_map(root, tmp_path / "other")
    before = _tree_hash(other)
    assert main(["map", "update", str(other), str(loc)]) == 2
    err = capsys.readouterr().err
    assert "another map" in err and str(loc / "metrics.json") in err and "Traceback" not in err
    assert _tree_hash(other) == before
    # --out onto an existing, different map: refused by identity, that map unchanged, the source too
    src_before = _tree_hash(root)
    assert main(["map", "update", str(root), str(loc), "--out", str(other)]) == 2
    err = capsys.readouterr().err
    assert "existing, different map" in err and str(other) in err
    assert _tree_hash(other) == before and _tree_hash(root) == src_before


def test_map_update_out_onto_a_file_or_a_read_only_place(tiny, tmp_path, capsys):
    root, loc, _ = tiny
    target = tmp_path / "a_file"
    target.write_text("not a map\n")
    assert main(["map", "update", str(root), str(loc), "--out", str(target)]) == 2
    err = capsys.readouterr().err
    assert str(target) in err and "not a folder" in err and "Traceback" not in err
    assert target.read_text() == "not a map\n"
    ro = Path("/sys/scenesig_test_map")          # sysfs: read-only even for root
    if os.access("/sys", os.W_OK) and ro.parent.exists():
        try:
            ro.mkdir()
        except OSError:
            pass
        else:
            ro.rmdir()
            pytest.skip("/sys is writable here: no read-only place to test")
    assert main(["map", "update", str(root), str(loc), "--out", str(ro)]) == 2
    err = capsys.readouterr().err
    assert str(ro) in err and "cannot be written" in err and "Traceback" not in err


def test_map_update_of_an_older_generation_needs_asking(tiny, tmp_path, capsys):
    """A localisation of generation 0 against the map at generation 1: refused (exit 2) unless
    --allow-older-generation; re-running the update that made generation 1 still changes nothing."""
    from scenesig.mapping.store import MapStore

    root, loc, _ = tiny
    work = tmp_path / "map"
    shutil.copytree(root, work)
    assert main(["map", "update", str(work), str(loc)]) == 0
    capsys.readouterr()
    store = MapStore.open(work)
    assert store.generation == 1 and store.map_id == MapStore.open(root).map_id   # the identity survives
    assert main(["map", "update", str(work), str(loc)]) == 0                       # already applied
    assert "already applied" in capsys.readouterr().out
    stale = tmp_path / "stale"
    shutil.copytree(loc, stale)
    m = json.loads((stale / "metrics.json").read_text())
    m["method_config"] = {**m["method_config"], "note": "another localisation of generation 0"}
    (stale / "metrics.json").write_text(json.dumps(m))
    before = _tree_hash(work)
    assert main(["map", "update", str(work), str(stale)]) == 2
    err = capsys.readouterr().err
    assert "generation 0" in err and "--allow-older-generation" in err
    assert _tree_hash(work) == before
    assert main(["map", "update", str(work), str(stale), "--allow-older-generation"]) == 0
    assert MapStore.open(work).generation in (1, 2)


def test_legacy_map_without_identity_is_read_and_updated(tiny, tmp_path):
    """A map written before identities: readable, its identity derived (the same for every reader); its
    localisations record that identity, and the update writes it into the manifest."""
    from scenesig.mapping.identity import derived_map_id
    from scenesig.mapping.store import MapStore
    from scenesig.mapping.update import check_localisations, read_localisation

    root, loc, _ = tiny
    old = tmp_path / "old"
    shutil.copytree(root, old)
    doc = json.loads((old / "manifest.json").read_text())
    del doc["map_id"]
    (old / "manifest.json").write_text(json.dumps(doc, indent=1, sort_keys=True))
    store = MapStore.open(old)
    assert store.map_id_derived and store.map_id == derived_map_id(doc)
    ours = tmp_path / "loc"
    shutil.copytree(loc, ours)
    m = json.loads((ours / "metrics.json").read_text())
    m.update({"map_id": store.map_id, "map": str(old)})
    (ours / "metrics.json").write_text(json.dumps(m))
    check_localisations(store, [read_localisation(ours)])            # accepted
    with pytest.raises(Exception, match="another map"):
        check_localisations(MapStore.open(root), [read_localisation(ours)])


# ------------------------------------------------------------------------------------- 6. smaller cases
def test_aerial_query_outside_every_tile_is_not_localised(tmp_path):
    """Images of one tile localised on a tile set without it: none reported localised, each named with
    the tile whose best match failed its checks; the same images on their own tile still localise."""
    import shutil as sh

    from test_aerial import _write_tiles

    from scenesig.aerial.geo import load_tiles
    from scenesig.aerial.localise import localise_sequence
    from scenesig.aerial.trials import write_sequence

    root = _write_tiles(tmp_path / "tiles", n=2)
    lines = (root / "map.csv").read_text().splitlines()

    def subset(name, k):
        d = tmp_path / name
        d.mkdir()
        sh.copy(root / f"t{k}.png", d / f"t{k}.png")
        (d / "map.csv").write_text("\n".join([lines[0], lines[1 + k]]) + "\n")
        return d

    only, own = subset("only_t0", 0), subset("only_t1", 1)
    rows = write_sequence(load_tiles(own), tmp_path / "seq", n=4, seed=2)     # images over t1 alone
    seq = tmp_path / "seq"
    on_t1 = rows
    s = localise_sequence(only, seq, tmp_path / "out", progress=False)
    assert s["images"] == len(on_t1) and s["localised"] == 0 and s["localised_fraction"] == 0.0
    assert set(s["not_localised"]) == {r["image"] for r in on_t1}
    assert all("t0.png" in why for why in s["not_localised"].values())
    track = (tmp_path / "out" / "track.csv").read_text().splitlines()
    head = track[0].split(",")
    assert all(line.split(",")[head.index("localised")] == "0" for line in track[1:])
    good = localise_sequence(own, seq, tmp_path / "good", progress=False)
    assert good["localised"] == len(on_t1) and good["not_localised"] == {}


def test_build_map_with_a_run_of_another_resolution_exits_2_and_leaves_nothing(tmp_path, capsys):
    from conftest import make_run

    from scenesig.surveys.geometry import Camera
    from scenesig.surveys.run import write_run

    ref, images = make_run(n_frames=6, size=(64, 48))
    write_run(ref, tmp_path / "ref", images=images)
    small, simg = make_run(n_frames=6, size=(32, 24), seed=1)
    small.name = "half"
    small.camera = Camera(25.0, 25.0, 15.5, 11.5, 32, 24)        # the same camera at half resolution
    write_run(small, tmp_path / "half", images=simg)
    out = tmp_path / "map"
    rc = main(["build-map", str(tmp_path / "ref"), str(tmp_path / "half"), "--reference", str(tmp_path / "ref"),
               "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and str(tmp_path / "half" / "run.toml") in err and "'half'" in err and "32x24" in err
    assert "Traceback" not in err and not out.exists()


def test_check_reports_every_problem_of_a_run(tmp_path):
    """A swapped frames.csv line does not stop the image checks; NaN and unsorted timestamps in one
    odometry.csv are both reported."""
    from conftest import make_run

    from scenesig.surveys.check import check_run
    from scenesig.surveys.run import write_run

    run, images = make_run(n_frames=12)
    write_run(run, tmp_path / "r", images=images)
    root = tmp_path / "r"
    lines = (root / "frames.csv").read_text().splitlines()
    lines[3], lines[4] = lines[4], lines[3]                            # a swapped line
    (root / "frames.csv").write_text("\n".join(lines) + "\n")
    (root / run.frame_files[9]).write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)   # and a corrupt image later
    odo = (root / "odometry.csv").read_text().splitlines()
    row = odo[3].split(",")
    odo[3] = ",".join(row[:2] + ["nan"] + row[3:])                     # NaN on line 4
    odo[7], odo[8] = odo[8], odo[7]                                    # unsorted at line 9
    (root / "odometry.csv").write_text("\n".join(odo) + "\n")
    problems, stats = check_run(root)
    found = {(Path(p.file).name, p.line, p.reason.split(":")[0].split(" (")[0]) for p in problems}
    assert ("frames.csv", 5, "timestamps must strictly increase") in found
    assert any(f == "000009.png" for f, _, _ in found), found
    assert ("odometry.csv", 4, "NaN or infinite value") in found
    assert ("odometry.csv", 9, "timestamps must strictly increase") in found
    assert stats["images_checked"] == 12


def test_fractions_are_clamped():
    """Shares of a distance summed segment by segment can round to 1.0000000000000002: clamped."""
    from scenesig.localiser.evaluation import coverage_metrics

    rng = np.random.default_rng(0)
    seen = 0
    for _ in range(4000):
        n = rng.integers(10, 400)
        s = np.cumsum(rng.uniform(0.01, 1.0, n)) + rng.uniform(0, 1e4)
        if float(np.diff(s).sum()) / float(s[-1] - s[0]) <= 1.0:
            continue
        seen += 1
        m = coverage_metrics(s, np.ones(n, bool))
        assert m["localised_fraction"] == 1.0 and m["blind_fraction_over_20m"] == 0.0
    assert seen, "no case rounding above 1 was drawn"
