"""Every reader survives fuzzing: any bytes, or a mutated valid file, give a valid object or a
``DataError`` naming the file -- never another exception, never a hang.

Readers: ``run.toml``, ``frames.csv``, ``odometry.csv``, ``gps.csv``, TUM trajectories, GRIEF ground truth
(sessions matrices and sequence displacements), the map manifest and place files, and the strict
image decoder.  Examples per reader: the ``scenesig-fuzz`` hypothesis profile (default suite) or
``scenesig-fuzz-heavy`` (``-m heavy``, or ``SCENESIG_FUZZ=heavy``); see tests/conftest.py.  Each
example runs under a 10 s alarm, so a reader that loops forever fails instead of hanging the suite.
"""
import os
import shutil
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis is needed (pip install -e '.[test]')")
from conftest import make_run  # noqa: E402
from hypothesis import (  # noqa: E402
    given,
    settings,
    strategies as st,  # noqa: E402
)

from scenesig.surveys.errors import DataError  # noqa: E402

HANG_SECONDS = 10
#: Byte strings a mutation splices in: separators, number-breakers, quotes, NUL, huge exponents.
SPLICES = [b",", b"\n", b"\r", b" ", b"\t", b"\x00", b"nan", b"inf", b"-", b"1e999", b"\"", b"[", b"]", b"=",
           b"{", b"}", b"#", b"0", b"9" * 40, b"\xff\xfe", b"\xc3", b"PK\x03\x04"]


@st.composite
def mutated(draw, valid: bytes):
    """``valid`` with 1-4 mutations: bit flips, byte changes, deletions, insertions, truncation, duplication."""
    b = bytearray(valid)
    for _ in range(draw(st.integers(1, 4))):
        if not b:
            break
        i = draw(st.integers(0, len(b) - 1))
        op = draw(st.sampled_from(["flip", "splice", "delete", "insert", "truncate", "duplicate"]))
        if op == "flip":
            b[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "splice":
            b[i:i + 1] = draw(st.sampled_from(SPLICES))
        elif op == "delete":
            del b[i:i + draw(st.integers(1, 32))]
        elif op == "insert":
            b[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "truncate":
            del b[i:]
        else:
            b[i:i] = b[i:i + draw(st.integers(1, 64))]
    return bytes(b)


# ------------------------------------------------------------------------------------------------ templates
def _survey_files(tmp: Path) -> dict:
    from scenesig.surveys.run import write_run

    run, images = make_run(n_frames=6)
    write_run(run, tmp / "run", images=images)
    return {name: (tmp / "run" / name).read_bytes()
            for name in ("run.toml", "frames.csv", "odometry.csv", "gps.csv", "groundtruth.tum")}


def _map_files(tmp: Path) -> dict:
    from test_store import CAM, PARAMS, T_VC, make_place, places_meta

    from scenesig.mapping.store import MapWriter

    w = MapWriter(tmp / "map", CAM, T_VC, PARAMS)
    for i in range(5):
        w.write_place(i, make_place(i, n=3, dim=8))
    w.finalise(places_meta())
    return {"manifest.json": (tmp / "map" / "manifest.json").read_bytes(),
            "place": (tmp / "map" / "places" / "place_0001.npz").read_bytes()}


def _image_files() -> dict:
    import cv2

    img = (np.add.outer(np.arange(48), np.arange(64)) % 256).astype(np.uint8)
    return {"jpeg": cv2.imencode(".jpg", img)[1].tobytes(), "png": cv2.imencode(".png", img)[1].tobytes()}


@pytest.fixture(scope="module")
def templates(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fuzz_templates")
    from test_grief import make_sequence, make_sessions

    out = {**_survey_files(tmp), **_map_files(tmp), **_image_files()}
    sessions = make_sessions(tmp / "sessions")
    sequence = make_sequence(tmp / "sequence")
    out["location_1.txt"] = (sessions / "ground_truth" / "location_1.txt").read_bytes()
    out["displacements.txt"] = (sequence / "season_01" / "displacements.txt").read_bytes()
    out["_dirs"] = {"sessions": sessions, "sequence": sequence, "map": tmp / "map"}
    return out


# ------------------------------------------------------------------------------------------------ readers
def _finite_increasing(t):
    t = np.asarray(t)
    assert t.ndim == 1 and len(t) and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)


def _valid_poses(P):
    P = np.asarray(P)
    assert P.ndim == 3 and P.shape[1:] == (4, 4) and np.all(np.isfinite(P))
    R = P[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)


def _read_meta(path, _):
    from scenesig.surveys.run import read_meta

    m = read_meta(path)
    assert m["camera"].width > 0 and m["camera"].fx > 0 and m["T_vehicle_camera"].shape == (4, 4)


def _read_frames(path, _):
    from scenesig.surveys.run import read_frames

    t, files, lines = read_frames(path)
    _finite_increasing(t)
    assert len(files) == len(t) == len(lines) and all(files)


def _read_odometry(path, _):
    from scenesig.surveys.run import read_odometry

    t, P = read_odometry(path)
    _finite_increasing(t)
    _valid_poses(P)


def _read_gps(path, _):
    from scenesig.surveys.run import read_gps

    g = read_gps(path)
    assert g.shape[1] == 4 and np.all(np.isfinite(g))
    _finite_increasing(g[:, 0])


def _read_tum(path, _):
    from scenesig.surveys.tum import read_tum

    t, P = read_tum(path)
    _finite_increasing(t)
    _valid_poses(P)


def _grief(layout):
    def read(path, dirs):
        from scenesig.surveys.grief import load

        ds = load(dirs[layout])
        for pair in ds.pairs():
            assert np.isfinite(ds.truth(pair))
    return read


def _manifest(path, dirs):
    from scenesig.mapping.store import MapStore

    store = MapStore.open(dirs["map"])
    assert all(np.isfinite(m.T_world_place).all() for m in store.places.values())
    for i in store.places:
        store.nearest_place(store.places[i].T_world_place)


def _place(path, _):
    from scenesig.mapping.store import decode_place

    data = decode_place(path.read_bytes(), path, 1)
    assert data.landmarks.shape[1] == 3


def _image(path, _):
    from scenesig.surveys.images import read_image

    img = read_image(path, gray=True)
    assert img.dtype == np.uint8 and img.ndim == 2


#: reader name -> (template key, file the fuzzed bytes go to (relative to its folder), read function)
READERS = {
    "run.toml": ("run.toml", None, _read_meta),
    "frames.csv": ("frames.csv", None, _read_frames),
    "odometry.csv": ("odometry.csv", None, _read_odometry),
    "gps.csv": ("gps.csv", None, _read_gps),
    "tum": ("groundtruth.tum", None, _read_tum),
    "grief-sessions": ("location_1.txt", ("sessions", "ground_truth/location_1.txt"), _grief("sessions")),
    "grief-sequence": ("displacements.txt", ("sequence", "season_01/displacements.txt"), _grief("sequence")),
    "manifest.json": ("manifest.json", ("map", "manifest.json"), _manifest),
    "place": ("place", None, _place),
    "jpeg": ("jpeg", None, _image),
    "png": ("png", None, _image),
}


def _alarm(signum, frame):
    raise TimeoutError(f"reader still running after {HANG_SECONDS} s: a hang")


def fuzz(reader: str, templates: dict, profile: str):
    key, target, read = READERS[reader]
    work = Path(tempfile.mkdtemp(prefix=f"fuzz_{reader}_"))
    dirs = {}
    for name, folder in templates["_dirs"].items():      # a private copy: the fuzzed file is overwritten
        dirs[name] = work / name
        shutil.copytree(folder, dirs[name])
    path = dirs[target[0]] / target[1] if target else work / key
    valid = templates[key]

    @settings(settings.get_profile(profile))
    @given(st.one_of(st.binary(max_size=1024), mutated(valid)))
    def survives(data):
        path.write_bytes(data)
        old = signal.signal(signal.SIGALRM, _alarm)
        signal.alarm(HANG_SECONDS)
        try:
            read(path, dirs)
        except DataError as exc:
            # the fuzzed file is the error's file, or (a disagreement between two files) named in it
            assert exc.path is not None and (Path(exc.path) == path or path.name in exc.message), \
                f"the error does not name {path}: {exc}"
        finally:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, old)

    try:
        path.write_bytes(valid)
        read(path, dirs)                                   # the template itself is valid
        survives()
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _profile(heavy: bool) -> str:
    return "scenesig-fuzz-heavy" if heavy or os.environ.get("SCENESIG_FUZZ") == "heavy" else "scenesig-fuzz"


@pytest.mark.parametrize("reader", list(READERS))
def test_reader_survives_fuzzing(reader, templates):
    fuzz(reader, templates, _profile(False))


@pytest.mark.heavy
@pytest.mark.parametrize("reader", list(READERS))
def test_reader_survives_heavy_fuzzing(reader, templates):
    fuzz(reader, templates, _profile(True))
