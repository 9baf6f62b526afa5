"""Aerial scene matching: exact histogram matching, affine from triples, MRSM-CC / SISM on synthetic
maps, the tile reader, the benchmark's JSON contract, sequence localisation."""
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from scenesig.aerial import affine as aff
from scenesig.aerial.geo import load_tiles
from scenesig.aerial.landmarks import LandmarkModel
from scenesig.aerial.mrsmcc import MRSMCC
from scenesig.aerial.sism import SISM
from scenesig.aerial.trials import cut_sensed, make_trial, photometric_change, sensed_centre
from scenesig.signatures.colour import exact_histogram_match, grid_edges, local_exact_histogram_match
from scenesig.surveys.errors import DataError

WILDNAV = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "wildnav"


def synthetic_map(seed=0, w=820, h=720):
    """A rural-looking BGR map: textured fields, grey roads, red and white roofs, dark trees."""
    rng = np.random.default_rng(seed)
    base = rng.random((h // 40 + 2, w // 40 + 2, 3)).astype(np.float32)
    img = cv2.resize(base, (w, h), interpolation=cv2.INTER_CUBIC)
    field = np.array([70, 160, 150], np.float32)                  # BGR yellow-green
    img = field[None, None] * (0.8 + 0.3 * img)
    img += rng.normal(0, 10, (h, w, 3)).astype(np.float32)
    for _ in range(6):                                            # roads
        p0 = tuple(int(v) for v in rng.integers(0, [w, h]))
        p1 = tuple(int(v) for v in rng.integers(0, [w, h]))
        cv2.line(img, p0, p1, (165, 170, 172), int(rng.integers(6, 14)))
    for _ in range(40):                                           # buildings
        x, y = int(rng.integers(0, w - 30)), int(rng.integers(0, h - 30))
        col = (40, 40, 170) if rng.random() < 0.5 else (230, 232, 235)
        cv2.rectangle(img, (x, y), (x + int(rng.integers(10, 30)), y + int(rng.integers(10, 30))),
                      col, -1)
    for _ in range(60):                                           # trees
        c = tuple(int(v) for v in rng.integers(0, [w, h]))
        cv2.circle(img, c, int(rng.integers(5, 20)), (30, 70, 35), -1)
    img = cv2.GaussianBlur(img, (3, 3), 0)
    return np.clip(img, 0, 255).astype(np.uint8)


def _hist(img):
    return [np.bincount(img[..., c].ravel(), minlength=256) for c in range(img.shape[2])]


# ------------------------------------------------------------------ exact histogram matching


def test_ehm_gives_colour_cast_image_the_reference_histogram_exactly():
    ref = synthetic_map(1, 200, 150)
    rng = np.random.default_rng(3)
    cast, _ = photometric_change(ref, rng)          # colour cast, gamma, haze, shadows, noise
    assert not all((a == b).all() for a, b in zip(_hist(cast), _hist(ref)))
    out = exact_histogram_match(cast, ref)
    assert out.shape == cast.shape and out.dtype == np.uint8
    for a, b in zip(_hist(out), _hist(ref)):
        np.testing.assert_array_equal(a, b)
    # The order of the pixels is kept: a darker source pixel never ends up brighter.
    for c in range(3):
        s, o = cast[..., c].ravel(), out[..., c].ravel().astype(int)
        vals = np.unique(s)
        lo = np.array([o[s == v].min() for v in vals])
        hi = np.array([o[s == v].max() for v in vals])
        assert np.all(hi[:-1] <= lo[1:])


def test_local_ehm_matches_every_window_exactly_and_rescales_other_sizes():
    ref = synthetic_map(2, 200, 150)
    cast, _ = photometric_change(ref, np.random.default_rng(5))
    out = local_exact_histogram_match(cast, ref, (5, 5))
    ys, xs = grid_edges(150, 5), grid_edges(200, 5)
    for i in range(5):
        for j in range(5):
            win = (slice(ys[i], ys[i + 1]), slice(xs[j], xs[j + 1]))
            for a, b in zip(_hist(out[win]), _hist(ref[win])):
                np.testing.assert_array_equal(a, b)
    # A reference of another size: counts are its histogram scaled to the source (eq. 2).
    big = cv2.resize(ref, (400, 300), interpolation=cv2.INTER_NEAREST)   # every pixel x4
    out2 = exact_histogram_match(cast, big)
    for a, b in zip(_hist(out2), _hist(ref)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError):
        local_exact_histogram_match(cast, big)


# ------------------------------------------------------------------ affine from the triple


def test_affine_from_triple_recovers_planted_transform():
    rng = np.random.default_rng(0)
    T = np.array([[0.95 * np.cos(0.1), -0.95 * np.sin(0.1), 310.0],
                  [0.95 * np.sin(0.1), 0.95 * np.cos(0.1), 122.0]])
    src = rng.uniform(0, 400, (3, 2))
    np.testing.assert_allclose(aff.affine_from_triple(src, aff.apply_affine(T, src)), T, atol=1e-9)
    # Collinear points have no solution.
    assert np.isnan(aff.affine_from_triple(np.array([[0, 0], [1, 1], [2, 2.0]]), src)).all()
    # Best-consistent triple among 6 good and 4 wrong registrations.
    src = rng.uniform(0, 400, (10, 2))
    dst = aff.apply_affine(T, src) + rng.normal(0, 0.3, (10, 2))
    dst[6:] += rng.uniform(60, 200, (4, 2))
    fit = aff.best_consistent_triple(src, dst)
    assert set(fit.triple) <= set(range(6))
    centre = np.array([199.5, 149.5])
    assert np.linalg.norm(aff.apply_affine(fit.transform, centre) - aff.apply_affine(T, centre)) < 2
    s, r = aff.scale_rotation(fit.transform)
    assert abs(s - 0.95) < 0.02 and abs(r - np.degrees(0.1)) < 1.0


# ------------------------------------------------------------------ MRSM-CC and SISM


@pytest.fixture(scope="module")
def synthetic_reference():
    ref = synthetic_map(7)
    return ref, MRSMCC().fit(ref), SISM().fit(ref)


def test_mrsmcc_and_sism_match_a_trial_without_photometric_change(synthetic_reference):
    ref, mrsmcc, sism = synthetic_reference
    centre = np.array([431.0, 352.0])
    sensed, A = cut_sensed(ref, centre, 1.04, 3.0)
    loc = mrsmcc.locate(sensed)
    assert loc.method == "multi-region" and loc.n_regions >= 4
    assert np.linalg.norm(loc.centre - centre) < 2.0
    assert abs(loc.rotation_deg - 3.0) < 1.0 and abs(loc.scale - 1 / 1.04) < 0.02
    # SISM models translation only (as in the paper): the same trial without rotation and scale.
    flat, _ = cut_sensed(ref, centre, 1.0, 0.0)
    assert np.linalg.norm(sism.locate(flat).centre - centre) < 2.0
    assert np.linalg.norm(mrsmcc.locate(flat).centre - centre) < 2.0


def test_mrsmcc_protocol_trial_with_photometric_change(synthetic_reference):
    ref, mrsmcc, _ = synthetic_reference
    tr = make_trial([ref], 3, seed=0)
    assert tr.photometric
    loc = mrsmcc.locate(tr.image)
    assert np.linalg.norm(loc.centre - tr.centre) < 5.0
    # The truth is the affine's image of the sensed centre.
    np.testing.assert_allclose(aff.apply_affine(tr.affine, sensed_centre(tr.image.shape)),
                               tr.centre, atol=1e-9)


def test_landmarks_rejects_unknown_config_and_finds_regions(synthetic_reference):
    ref, mrsmcc, _ = synthetic_reference
    with pytest.raises(ValueError):
        LandmarkModel({"no_such_key": 1})
    regions = mrsmcc.landmarks.regions(ref[:300, :400])
    assert len(regions) >= 4
    assert all(31.5 <= r.x <= 400 - 32.5 and 31.5 <= r.y <= 300 - 32.5 for r in regions)


# ------------------------------------------------------------------ tiles and geometry


def _write_tiles(root: Path, n=2, w=820, h=720):
    root.mkdir(parents=True, exist_ok=True)
    lines = ["Filename,Top_left_lat,Top_left_lon,Bottom_right_lat,Bottom_right_long"]
    for i in range(n):
        cv2.imwrite(str(root / f"t{i}.png"), synthetic_map(10 + i, w, h))
        lon0 = 22.46 + i * 0.0018
        lines.append(f'"t{i}.png",60.4030,{lon0:.6f},60.4021,{lon0 + 0.0018:.6f}')
    (root / "map.csv").write_text("\n".join(lines) + "\n")
    return root


def test_tiles_pixel_latlon_local_round_trip(tmp_path):
    tiles = load_tiles(_write_tiles(tmp_path / "tiles"))
    t = tiles[0]
    xy = np.array([[0.0, 0.0], [410.3, 250.7], [819.0, 719.0]])
    ll = t.pixel_to_latlon(xy)
    np.testing.assert_allclose(t.latlon_to_pixel(ll), xy, atol=1e-6)
    np.testing.assert_allclose(t.pixel_to_latlon([-0.5, -0.5]), t.top_left, atol=1e-12)
    en = tiles.latlon_to_local(ll)
    np.testing.assert_allclose(tiles.local_to_latlon(en), ll, atol=1e-10)
    # 0.0009 deg of latitude is about 100 m; 0.0018 deg of longitude at 60.4 N about 99 m.
    mx, my = t.metres_per_pixel()
    assert abs(my * 720 - 100.2) < 0.5 and abs(mx * 820 - 99.1) < 0.5
    assert tiles.tile_at(tiles[1].centre_latlon) is tiles[1]


@pytest.mark.parametrize("row, message", [
    ('"t0.png",60.4030,abc,60.4021,22.4618', "not a number"),
    ('"t0.png",60.4020,22.46,60.4030,22.4618', "north-west"),
    ('"missing.png",60.4030,22.46,60.4021,22.4618', "not found"),
    ('"t0.png",60.4030,nan,60.4021,22.4618', "not finite"),
])
def test_map_csv_errors_name_the_file(tmp_path, row, message):
    root = _write_tiles(tmp_path / "tiles", n=1)
    (root / "map.csv").write_text(
        "Filename,Top_left_lat,Top_left_lon,Bottom_right_lat,Bottom_right_long\n" + row + "\n")
    with pytest.raises(DataError, match=message):
        load_tiles(root)
    (root / "map.csv").write_text("Filename,Top_left_lat\n")
    with pytest.raises(DataError, match="missing column"):
        load_tiles(root)


def test_real_wildnav_tiles_geometry():
    if not WILDNAV.is_dir():
        pytest.skip(f"{WILDNAV} not found (real data lives beside the project in ../shared/data)")
    tiles = load_tiles(WILDNAV)
    assert len(tiles) == 8
    mx, my = tiles[0].metres_per_pixel()
    assert 0.12 < mx < 0.15 and 0.12 < my < 0.15         # the README's ~0.135 m/px
    # Neighbouring tiles adjoin: 00's east edge is 01's west edge (within a metre).
    e00 = tiles.latlon_to_local([tiles[0].centre_latlon[0], tiles[0].bottom_right[1]])
    w01 = tiles.latlon_to_local([tiles[1].centre_latlon[0], tiles[1].top_left[1]])
    assert abs(e00[0] - w01[0]) < 1.0


# ------------------------------------------------------------------ benchmark and sequence


def test_benchmark_json_contract_and_determinism(tmp_path):
    from scenesig.benchmarks.aerial import run_benchmark

    root = _write_tiles(tmp_path / "tiles")
    out = tmp_path / "out" / "aerial.json"
    doc = run_benchmark(root, ["mrsmcc", "sism", "orb"], trials=2, seed=4, json_path=out,
                        figure_dir=tmp_path / "fig", progress=False)
    assert json.loads(out.read_text()) == json.loads(json.dumps(doc))
    assert {"tiles", "trials", "success_px", "methods"} <= set(doc)
    assert doc["tiles"] == 2 and doc["trials"] == 2 and doc["success_px"] == 25
    for m in ("mrsmcc", "sism", "orb"):
        assert set(doc["methods"][m]) == {"success_rate", "mean_error_px", "median_error_px",
                                          "seconds_per_trial", "per_tile"}
        pt = doc["methods"][m]["per_tile"]
        assert sum(v["trials"] for v in pt.values()) == 2 and set(pt) <= {"t0.png", "t1.png"}
    assert doc["methods"]["mrsmcc"]["success_rate"] == 1.0
    assert (tmp_path / "fig" / "aerial_errors.png").is_file()
    assert len((out.parent / "trials.csv").read_text().splitlines()) == 3
    again = run_benchmark(root, ["mrsmcc", "sism", "orb"], trials=2, seed=4, progress=False)
    for m in ("mrsmcc", "sism", "orb"):
        a, b = doc["methods"][m], again["methods"][m]
        assert a["success_rate"] == b["success_rate"] and a["median_error_px"] == b["median_error_px"]
    with pytest.raises(ValueError, match="unknown method"):
        run_benchmark(root, ["nope"], trials=1, progress=False)


def test_benchmark_folds_report_held_out_tiles_only(tmp_path, capsys):
    """--folds K: tile i is in fold i mod K; settings chosen on the other folds' tiles; every trial
    of a fold is drawn over its held-out tiles."""
    from scenesig import cli
    from scenesig.benchmarks import aerial as bench

    root = _write_tiles(tmp_path / "tiles", n=3)
    doc = bench.run_benchmark(root, ["sism", "orb"], trials=4, seed=3, json_path=tmp_path / "o" / "a.json",
                              progress=False, folds=2, search_trials=1)
    assert [f["test_tiles"] for f in doc["folds"]] == [["t0.png", "t2.png"], ["t1.png"]]
    assert [f["train_tiles"] for f in doc["folds"]] == [["t1.png"], ["t0.png", "t2.png"]]
    for f in doc["folds"]:
        for m in ("sism", "orb"):
            assert len(f["search"][m]) == len(bench.SEARCH[m])
            assert f["chosen"][m] in bench.SEARCH[m]
    rows = (tmp_path / "o" / "trials.csv").read_text().splitlines()[1:]
    # trials 0 and 2 belong to fold 0 (tiles t0, t2), trials 1 and 3 to fold 1 (tile t1)
    tile_of = {int(r.split(",")[0]): r.split(",")[1] for r in rows}
    assert sorted(tile_of) == [0, 1, 2, 3]
    assert {tile_of[0], tile_of[2]} <= {"t0.png", "t2.png"} and tile_of[1] == tile_of[3] == "t1.png"
    assert sum(v["trials"] for v in doc["methods"]["orb"]["per_tile"].values()) == 4
    assert cli.main(["aerial", "bench", str(root), "--folds", "5", "--methods", "sism", "--no-progress"]) == 2
    assert "--folds must be between 2" in capsys.readouterr().err


def test_choose_defaults_searches_all_tiles(tmp_path, capsys):
    """--choose-defaults: the folds' search on every tile; reports the chosen candidate and whether the
    methods' defaults are it.  Every method's defaults are one of its search candidates."""
    from scenesig import cli
    from scenesig.benchmarks import aerial as bench

    for m in bench.SEARCH:
        if bench.SEARCH[m] != [{}]:
            assert any(bench._same(bench.searched_defaults(m), c) for c in bench.SEARCH[m]), m
    root = _write_tiles(tmp_path / "tiles", n=2)
    doc = bench.choose_defaults(root, ["sism", "orb"], search_trials=1, json_path=tmp_path / "c.json",
                                progress=False)
    assert doc["tiles"] == ["t0.png", "t1.png"] and json.loads((tmp_path / "c.json").read_text()) == \
        json.loads(json.dumps(doc, default=bench._jsonable))
    for m in ("sism", "orb"):
        assert len(doc["search"][m]) == len(bench.SEARCH[m]) and doc["chosen"][m] in bench.SEARCH[m]
        assert doc["defaults"][m] == bench.searched_defaults(m)
        assert doc["defaults_are_chosen"][m] == bench._same(doc["defaults"][m], doc["chosen"][m])
    assert bench._same({"cc_grid": (3, 3)}, {"cc_grid": [3, 3]}) and not bench._same((3, 3), (5, 5))
    assert cli.main(["aerial", "bench", str(root), "--choose-defaults", "--folds", "2", "--no-progress"]) == 2
    assert "takes no --folds" in capsys.readouterr().err


def test_search_rule_prefers_success_then_speed():
    from scenesig.benchmarks.aerial import choose

    r = [{"success_rate": 0.9, "seconds_per_trial": 0.1}, {"success_rate": 0.95, "seconds_per_trial": 0.3},
         {"success_rate": 0.95, "seconds_per_trial": 0.2}]
    assert choose(r) == 2


def test_localise_sequence_writes_track(tmp_path):
    from scenesig.aerial.localise import localise_sequence
    from scenesig.aerial.trials import write_sequence

    root = _write_tiles(tmp_path / "tiles")
    tiles = load_tiles(root)
    rows = write_sequence(tiles, tmp_path / "seq", n=3, seed=2)
    first = (rows[0]["lat"], rows[0]["lon"])
    summary = localise_sequence(root, tmp_path / "seq", tmp_path / "out", prior=first,
                                progress=False)
    assert summary["images"] == 3 and summary["localised"] == 3
    assert summary["median_error_m"] < 1.0
    lines = (tmp_path / "out" / "track.csv").read_text().splitlines()
    assert lines[0].startswith("image,tile,x_px,y_px,lat,lon,east_m,north_m")
    assert len(lines) == 4
    assert (tmp_path / "out" / "track.png").is_file()
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no images"):
        localise_sequence(root, tmp_path / "empty", tmp_path / "o2", progress=False)


def test_cli_aerial_commands(tmp_path, capsys):
    from scenesig import cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["aerial", "bench", "--help"])
    assert exc.value.code == 0
    assert "scenesig aerial bench" in capsys.readouterr().out
    assert cli.main(["aerial", "localise", str(tmp_path / "missing"), str(tmp_path),
                     "--out", str(tmp_path / "o")]) == 2
    assert "tile folder not found" in capsys.readouterr().err
    root = _write_tiles(tmp_path / "tiles", n=1)
    assert cli.main(["aerial", "simulate", str(root), str(tmp_path / "seq"), "--images", "2"]) == 0
    assert sorted(p.name for p in (tmp_path / "seq").iterdir()) == ["0000.png", "0001.png",
                                                                   "truth.csv"]
