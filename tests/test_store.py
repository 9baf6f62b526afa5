"""The map store (mapping/store.py): round trip, determinism, atomic resume, integrity errors, lazy cache."""
import hashlib
import json
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from scenesig.cli import main
from scenesig.mapping.store import (
    FORMAT_VERSION,
    MapStore,
    MapWriter,
    PlaceData,
    PlaceMeta,
    decode_keyframe,
    encode_keyframe,
)
from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import CAMERA_FROM_VEHICLE_AXES, Camera, make_pose, rot_z

ROOT = Path(__file__).resolve().parents[1]
CAM = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
T_VC = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.5, 0.0, 1.5])
PARAMS = {"place_spacing_m": 10.0, "window_m": 10.0, "refine": {"huber_alpha": 2.0}}
N_PLACES = 5


def make_place(i, n=12, dim=400, exact=False):
    """Deterministic place data; with ``exact`` every float is representable in its stored type.

    Like a real bank, the filters are one flat float32 vector (large: a float16 candidate) next to small
    per-classifier arrays, strings and scalars (always stored exactly).
    """
    rng = np.random.default_rng(100 + i)
    w = (rng.standard_normal(n * dim) * 0.05).astype(np.float32)
    w[::7] *= 1e-4  # tiny weights (float16 subnormals): fine for the scores, not per element
    b = np.linspace(-1, 1, n).astype(np.float32)
    lm = rng.uniform(-20, 60, (n, 3))
    if exact:
        # float16 with the 6 low mantissa bits zero: exact with the fewest mantissa bits the store keeps (4)
        w = (w.astype(np.float16).view(np.uint16) & np.uint16(0xFFC0)).view(np.float16).astype(np.float32)
        b = b.astype(np.float16).astype(np.float32)
        lm = lm.astype(np.float32).astype(np.float64)
    A = rng.standard_normal((n, 3, 3))
    cov = np.einsum("nij,nkj->nik", A, A) + 0.1 * np.eye(3)
    if exact:
        cov = cov.astype(np.float32).astype(np.float64)
    img = (np.add.outer(np.arange(120), np.arange(160)) % 256).astype(np.uint8)
    img[20 + i: 60 + i, 30:90] = 255 - img[20 + i: 60 + i, 30:90]
    return PlaceData(
        bank_arrays={"weights": w, "bias": b, "kind_names": np.array(["strip", "square"]),
                     "hog_clip": np.array(0.2), "box": rng.uniform(0, 640, (n, 4)),
                     "shapes": rng.integers(0, 64, (n, 4)).astype(np.int16),
                     "hog_norm": np.full(n, 123456.789)},  # above float16's range: kept at float32
        landmarks=lm, covariances=cov, classifier_ids=np.arange(n) * 3 + i,
        keyframe=encode_keyframe(img), meta={"reference_run": "run_a", "frame": 40 + i})


def places_meta():
    return [{"index": i, "T_world_place": make_pose(rot_z(0.05 * i), [10.0 * i, 0.5 * i, 0.0]),
             "neighbours": [j for j in (i - 1, i + 1) if 0 <= j < N_PLACES]} for i in range(N_PLACES)]


def build(root, **kw):
    w = MapWriter(root, CAM, T_VC, PARAMS, **kw)
    for i in range(N_PLACES):
        if not w.has_place(i):
            w.write_place(i, make_place(i))
    w.finalise(places_meta())
    return root


def folder_bytes(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(Path(root).rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------------------ round trip
def test_round_trip_is_identical(tmp_path):
    w = MapWriter(tmp_path / "m", CAM, T_VC, PARAMS)
    data = {i: make_place(i, exact=True) for i in range(N_PLACES)}
    for i, d in data.items():
        w.write_place(i, d)
    w.finalise(places_meta())
    store = MapStore.open(tmp_path / "m", verify=True)
    assert store.camera == CAM and store.params == PARAMS and store.format_version == FORMAT_VERSION
    np.testing.assert_array_equal(store.T_vehicle_camera, T_VC)
    assert list(store.places) == list(range(N_PLACES))
    for m in places_meta():
        pm = store.places[m["index"]]
        np.testing.assert_array_equal(pm.T_world_place, m["T_world_place"])
        assert list(pm.neighbours) == m["neighbours"]
    for i, d in data.items():
        got = store.load_place(i)
        assert set(got.bank_arrays) == set(d.bank_arrays)
        for k, v in d.bank_arrays.items():
            assert got.bank_arrays[k].dtype == v.dtype and got.bank_arrays[k].shape == v.shape, k
            np.testing.assert_array_equal(got.bank_arrays[k], v)
        for a, b in ((got.landmarks, d.landmarks), (got.covariances, d.covariances),
                     (got.classifier_ids, d.classifier_ids)):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
        assert got.keyframe == d.keyframe and got.meta == d.meta
        assert got.keyframe_image().shape == (120, 160)


def _stored_kind(path, key):
    """How a bank array is on disk: 'float16' (byte planes, with the mantissa bits kept) or its dtype."""
    with np.load(path) as z:
        fmt = json.loads(z["format"].tobytes())
        enc = fmt.get("float16_planes", {}).get(f"bank/{key}")
        if enc is not None:
            assert z[f"bank/{key}"].dtype == np.uint8 and z[f"bank/{key}"].shape[0] == 2
            return "float16", enc["mantissa_bits"]
        return str(z[f"bank/{key}"].dtype), None


def test_floats_are_stored_small_only_within_tolerance(tmp_path):
    d = make_place(0)
    w = MapWriter(tmp_path / "m", CAM, T_VC, PARAMS)
    rec = w.write_place(0, d)
    kind, bits = _stored_kind(tmp_path / "m" / rec["file"], "weights")
    assert kind == "float16" and 4 <= bits < 10  # fewer mantissa bits than float16 within the tolerance
    with np.load(tmp_path / "m" / rec["file"]) as z:
        for k in ("bias", "box", "hog_clip", "hog_norm"):  # small arrays: stored exactly
            assert z[f"bank/{k}"].dtype == d.bank_arrays[k].dtype, k
        assert z["bank/shapes"].dtype == np.int16 and z["bank/kind_names"].dtype.kind == "U"
        assert z["landmarks"].dtype == np.float32 and z["covariances"].dtype == np.float32
    w.finalise([places_meta()[0] | {"neighbours": []}])
    got = MapStore.open(tmp_path / "m").load_place(0)
    wt = d.bank_arrays["weights"].reshape(12, -1)
    rel = np.linalg.norm(got.bank_arrays["weights"].reshape(12, -1) - wt, axis=1) / np.linalg.norm(wt, axis=1)
    assert got.bank_arrays["weights"].dtype == np.float32 and rel.max() <= 4e-3
    # a tighter tolerance keeps more bits, plain float16 (10 bits) at float16's own rounding
    w = MapWriter(tmp_path / "tight", CAM, T_VC, PARAMS, float16_tol=4e-4)
    assert _stored_kind(tmp_path / "tight" / w.write_place(0, d)["file"], "weights") == ("float16", 10)
    for k in ("bias", "box", "hog_clip", "kind_names"):
        np.testing.assert_array_equal(got.bank_arrays[k], d.bank_arrays[k])
    np.testing.assert_allclose(got.landmarks, d.landmarks, rtol=1e-6, atol=1e-6)

    # measured on the scores themselves: a tolerance float16 cannot meet keeps the bank at float32
    feats = np.random.default_rng(0).random((200, 400))

    def scores(arrays):
        return feats @ arrays["weights"].astype(np.float64).reshape(12, -1).T + arrays["bias"]

    for tol, expect in ((1e-1, "float16"), (1e-6, "float32")):
        w = MapWriter(tmp_path / f"s{tol}", CAM, T_VC, PARAMS, score_fn=scores, score_tol=tol)
        rec = w.write_place(0, d)
        assert _stored_kind(tmp_path / f"s{tol}" / rec["file"], "weights")[0] == expect
    # the per-element view would have refused float16 here (tiny weights lose their relative precision)
    w16 = d.bank_arrays["weights"].astype(np.float16).astype(np.float32)
    tiny = d.bank_arrays["weights"][::7]
    assert np.max(np.abs(w16[::7] - tiny) / np.abs(tiny)) > 1e-3


def test_place_files_are_deterministic_zip(tmp_path):
    a = folder_bytes(build(tmp_path / "a"))
    b = folder_bytes(build(tmp_path / "b"))
    # two builds are two maps: the same bytes but for the identity each drew (mapping.identity)
    ma, mb = json.loads(a.pop("manifest.json")), json.loads(b.pop("manifest.json"))
    assert ma.pop("map_id") != mb.pop("map_id") and ma == mb
    assert a == b and "journal.jsonl" not in a
    with zipfile.ZipFile(tmp_path / "a" / "places" / "place_0003.npz") as zf:
        names = zf.namelist()
        assert names == sorted(names)
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    for p in manifest["places"]:
        assert hashlib.sha256(a[p["file"]]).hexdigest() == p["sha256"]
        assert p["bytes"] == len(a[p["file"]]) and p["signatures"] == 12
    assert manifest["software"] and manifest["params"] == PARAMS


# ------------------------------------------------------------------------------------------- kill and resume
KILL_SCRIPT = textwrap.dedent("""
    import os, signal, sys
    sys.path.insert(0, {tests!r})
    import scenesig.mapping.store as S
    import scenesig.surveys.io as IO  # the atomic writer the store uses
    from test_store import CAM, T_VC, PARAMS, make_place
    mode = {mode!r}
    def die():
        os.kill(os.getpid(), signal.SIGKILL)
    if mode == "before_rename":      # killed with the temp file written but not yet renamed
        real = os.replace
        def replace(src, dst):
            if str(dst).endswith("place_0002.npz"):
                die()
            real(src, dst)
        IO.os.replace = replace
    elif mode == "mid_temp_write":   # killed half-way through writing the temp file
        real_write = IO._write_all
        def half(fd, data):
            if "place_0002" in os.readlink(f"/proc/self/fd/{{fd}}"):
                real_write(fd, bytes(data)[: len(data) // 2]); die()
            real_write(fd, data)
        IO._write_all = half
    elif mode == "after_rename":     # killed after the rename, before the journal line
        real = IO._fsync_dir
        def fsync_dir(folder):
            if (folder / "place_0002.npz").exists():
                die()
            real(folder)
        IO._fsync_dir = fsync_dir
    w = S.MapWriter(sys.argv[1], CAM, T_VC, PARAMS)
    for i in range(5):
        w.write_place(i, make_place(i))
    if mode == "torn_journal":       # killed while appending the journal line of place 3
        with open(os.path.join(sys.argv[1], "journal.jsonl"), "a") as f:
            f.write('{{"index": 3, "file": "places/pla')
        die()
    w.finalise([])
""")


@pytest.mark.skipif(sys.platform == "win32", reason="needs POSIX SIGKILL")
@pytest.mark.parametrize("mode", ["before_rename", "mid_temp_write", "after_rename", "torn_journal"])
def test_killed_build_resumes_to_identical_bytes(tmp_path, mode):
    reference = folder_bytes(build(tmp_path / "ref"))
    root = tmp_path / "m"
    script = KILL_SCRIPT.format(tests=str(ROOT / "tests"), mode=mode)
    proc = subprocess.run([sys.executable, "-c", script, str(root)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == -9, proc.stderr  # really killed (SIGKILL), not a clean exit
    assert not (root / "manifest.json").exists()
    if mode in ("before_rename", "mid_temp_write"):
        assert list((root / "places").glob(".place_0002.npz.*.tmp")), "the kill should leave a temp file"
    with pytest.raises(DataError, match="interrupted"):
        MapStore.open(root)

    killed_id = json.loads((root / "journal.jsonl").read_text().splitlines()[0])["header"]["map_id"]
    w = MapWriter(root, CAM, T_VC, PARAMS)
    done = [0, 1, 2, 3, 4] if mode == "torn_journal" else [0, 1]
    assert w.written == done and w.map_id == killed_id     # the resumed build keeps the map's identity
    assert not list(root.rglob("*.tmp"))
    build(root)
    got = folder_bytes(root)
    ma, mb = json.loads(got.pop("manifest.json")), json.loads(reference.pop("manifest.json"))
    assert ma.pop("map_id") == killed_id != mb.pop("map_id") and ma == mb
    assert got == reference


def test_resume_refuses_different_settings(tmp_path):
    root = tmp_path / "m"
    w = MapWriter(root, CAM, T_VC, PARAMS)
    w.write_place(0, make_place(0))
    with pytest.raises(DataError, match="journal.jsonl.*params"):
        MapWriter(root, CAM, T_VC, {**PARAMS, "window_m": 5.0})
    w2 = MapWriter(root, CAM, T_VC, {**PARAMS, "window_m": 5.0}, overwrite=True)
    assert w2.written == []
    # a finished map is also protected, and re-opening it with the same settings skips every place
    build(tmp_path / "done")
    with pytest.raises(DataError, match="manifest.json.*camera"):
        MapWriter(tmp_path / "done", CAM.scaled(0.5), T_VC, PARAMS)
    assert MapWriter(tmp_path / "done", CAM, T_VC, PARAMS).written == list(range(N_PLACES))


def test_resume_redoes_a_place_whose_file_was_damaged(tmp_path):
    root = tmp_path / "m"
    w = MapWriter(root, CAM, T_VC, PARAMS)
    for i in range(3):
        w.write_place(i, make_place(i))
    (root / "places" / "place_0001.npz").write_bytes(b"garbage")
    assert MapWriter(root, CAM, T_VC, PARAMS).written == [0, 2]


# ----------------------------------------------------------------------------------------- integrity errors
def test_checksum_mismatch_names_the_file(tmp_path):
    root = build(tmp_path / "m")
    f = root / "places" / "place_0002.npz"
    raw = bytearray(f.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # one flipped byte, same size
    f.write_bytes(bytes(raw))
    store = MapStore.open(root)  # lazy: opening does not read place files
    store.load_place(1)
    with pytest.raises(DataError, match=r"place_0002\.npz: checksum mismatch"):
        store.load_place(2)
    with pytest.raises(DataError, match=r"place_0002\.npz"):
        MapStore.open(root, verify=True)
    assert main(["map", "verify", str(root)]) == 2  # the CLI's one DataError exit status


def test_corrupt_place_file_gives_clear_error(tmp_path):
    root = build(tmp_path / "m")
    f = root / "places" / "place_0004.npz"
    f.write_bytes(f.read_bytes()[:300])  # truncated
    doc = json.loads((root / "manifest.json").read_text())
    doc["places"][4]["sha256"] = hashlib.sha256(f.read_bytes()).hexdigest()  # so parsing is what fails
    (root / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match=r"place_0004\.npz: not a readable place file"):
        MapStore.open(root).load_place(4)
    (root / "places" / "place_0003.npz").unlink()
    with pytest.raises(DataError, match=r"place_0003\.npz: place 3's file .* is missing"):
        MapStore.open(root).load_place(3)


def test_manifest_errors(tmp_path):
    root = build(tmp_path / "m")
    mpath = root / "manifest.json"
    good = mpath.read_text()
    doc = json.loads(good)
    doc["format_version"] = 99
    mpath.write_text(json.dumps(doc))
    with pytest.raises(DataError, match=r"manifest\.json: map format version 99 is not supported"):
        MapStore.open(root)
    mpath.write_text(good[:200])
    with pytest.raises(DataError, match=r"manifest\.json:\d+: invalid JSON"):
        MapStore.open(root)
    doc = json.loads(good)
    doc["places"][0]["neighbours"] = [42]
    mpath.write_text(json.dumps(doc))
    with pytest.raises(DataError, match="neighbours \\[42\\]"):
        MapStore.open(root)
    doc = json.loads(good)
    doc["places"][0]["file"] = "../elsewhere.npz"
    mpath.write_text(json.dumps(doc))
    with pytest.raises(DataError, match="inside the map folder"):
        MapStore.open(root)
    with pytest.raises(DataError, match="no manifest"):
        MapStore.open(tmp_path / "nothing")


# ---------------------------------------------------------------------------------------------- lazy access
def test_places_load_lazily_through_an_lru_cache(tmp_path):
    root = build(tmp_path / "m")
    store = MapStore.open(root, cache_size=2)
    assert store.cache_info() == (0, 0, 0, 2)
    a = store.load_place(0)
    assert store.load_place(0) is a
    store.load_place(1)
    store.load_place(2)  # evicts place 0 (least recently used)
    assert store.cache_info() == (1, 3, 2, 2)
    assert store.load_place(0) is not a
    assert store.cache_info().misses == 4
    with pytest.raises(ValueError):
        a.landmarks[0, 0] = 1.0  # shared through the cache: read-only
    with pytest.raises(KeyError):
        store.load_place(99)
    assert main(["map", "verify", str(root)]) == 0


def test_nearest_place_uses_position_and_heading(tmp_path):
    root = tmp_path / "m"
    w = MapWriter(root, CAM, T_VC, PARAMS)
    meta = []
    # an out-and-back route: places 0-2 eastbound, 3-5 westbound on the other lane
    for i in range(6):
        x = 10.0 * i if i < 3 else 10.0 * (5 - i)
        yaw = 0.0 if i < 3 else np.pi
        w.write_place(i, make_place(i, n=2))
        meta.append(PlaceMeta(i, make_pose(rot_z(yaw), [x, 0.0 if i < 3 else 4.0, 0]), ()))
    w.finalise(meta)
    store = MapStore.open(root)
    assert store.nearest_place([11.0, 3.9]) == 4  # by position only
    assert store.nearest_place(make_pose(rot_z(0.1), [11.0, 3.9, 0])) == 1  # eastbound: place 1
    assert store.nearest_place(make_pose(rot_z(np.pi), [1.0, 0.2, 0])) == 5
    assert store.nearest_place(make_pose(rot_z(np.pi), [1.0, 0.2, 0]), max_heading_diff=None) == 0


def test_finalise_checks_the_place_list(tmp_path):
    w = MapWriter(tmp_path / "m", CAM, T_VC, PARAMS)
    for i in range(2):
        w.write_place(i, make_place(i))
    pm = places_meta()[:2]
    with pytest.raises(ValueError, match=r"places \[2\] were never written"):
        w.finalise(places_meta()[:3])
    with pytest.raises(ValueError, match=r"places \[1\] were written but are not"):
        w.finalise([pm[0] | {"neighbours": []}])
    with pytest.raises(ValueError, match="unknown places"):
        w.finalise([pm[0] | {"neighbours": [7]}, pm[1]])
    with pytest.raises(ValueError, match="classifier_ids"):
        PlaceData({}, np.zeros((2, 3)), np.zeros((2, 3, 3)), np.zeros(3, int))
    with pytest.raises(ValueError, match="only numeric"):
        PlaceData({"names": np.array(["a"], dtype=object)}, np.zeros((0, 3)), np.zeros((0, 3, 3)), [])


def test_keyframe_helpers():
    img = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    data = encode_keyframe(img)
    out = decode_keyframe(data)
    assert out.shape == (120, 160) and out.dtype == np.uint8
    assert data == encode_keyframe(img)  # deterministic
    assert len(data) < 30_000
    assert decode_keyframe(None) is None


def test_map_identity_drawn_at_build_kept_on_resume_and_derived_for_old_maps(tmp_path):
    """A map's identity is drawn when its build starts, kept by a resumed build (journal), and for a map
    written before identities existed derived from its manifest, the same for every reader."""
    from scenesig.mapping.identity import derived_map_id

    w = MapWriter(tmp_path / "m", CAM, T_VC, PARAMS)
    w.write_place(0, make_place(0))
    first = w.map_id
    again = MapWriter(tmp_path / "m", CAM, T_VC, PARAMS)        # an interrupted build, resumed
    assert again.map_id == first
    again.write_place(1, make_place(1))
    again.finalise([{"index": i, "T_world_place": np.eye(4), "neighbours": []} for i in (0, 1)])
    store = MapStore.open(tmp_path / "m")
    assert store.map_id == first and not store.map_id_derived
    other = MapWriter(tmp_path / "n", CAM, T_VC, PARAMS)
    assert other.map_id != first
    # an old map: no map_id in its manifest -> derived deterministically, stable across readers
    doc = json.loads((tmp_path / "m" / "manifest.json").read_text())
    del doc["map_id"]
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(doc))
    old = MapStore.open(tmp_path / "m")
    assert old.map_id_derived and old.map_id == derived_map_id(doc) == MapStore.open(tmp_path / "m").map_id
    doc["map_id"] = 7
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match="map_id"):
        MapStore.open(tmp_path / "m")
