"""Faults: corrupt images never pass unnoticed, ``scenesig check`` vets runs and maps, a full disk or a
read-only folder loses nothing, and real-time replay keeps up with both cores loaded.

(The readers' fuzzing is tests/test_fuzz_readers.py.)
"""
import errno
import json
import logging
import multiprocessing
import os
import pickle
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import make_run
from faultinject import disk_full, folder_bytes, read_only

from scenesig.surveys.errors import CorruptImageError, DataError, OutputError
from scenesig.surveys.images import decode_image, read_image


def _jpeg(w=640, h=480, seed=0) -> bytes:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (7, 7), 2)
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


# --------------------------------------------------------------------------------------- strict decoding
def test_truncated_jpeg_is_an_error_where_opencv_returns_a_grey_frame(tmp_path):
    data = _jpeg()
    (tmp_path / "cut.jpg").write_bytes(data[: int(len(data) * 0.6)])
    lenient = cv2.imread(str(tmp_path / "cut.jpg"), cv2.IMREAD_COLOR)
    assert lenient is not None and lenient.shape == (480, 640, 3)      # the hole: a partly grey frame
    with pytest.raises(CorruptImageError, match="corrupt or truncated JPEG") as e:
        read_image(tmp_path / "cut.jpg")
    assert e.value.path == tmp_path / "cut.jpg"
    # the intact frame decodes to OpenCV's pixels exactly (colour and gray)
    (tmp_path / "ok.jpg").write_bytes(data)
    for gray, flag in ((False, cv2.IMREAD_COLOR), (True, cv2.IMREAD_GRAYSCALE)):
        np.testing.assert_array_equal(read_image(tmp_path / "ok.jpg", gray),
                                      cv2.imdecode(np.frombuffer(data, np.uint8), flag))


def test_corrupt_jpeg_data_is_an_error():
    data = bytearray(_jpeg(seed=1))
    # a marker inside the entropy-coded data: libjpeg warns "extraneous bytes before marker", decodes on
    pos = len(data) // 2
    data[pos:pos + 2] = b"\xff\xd3"
    with pytest.raises(CorruptImageError):
        decode_image(bytes(data), "frame.jpg")


@pytest.mark.parametrize("damage", ["truncate", "crc", "no_iend"])
def test_damaged_png_is_an_error(damage, tmp_path):
    img = (np.add.outer(np.arange(120), np.arange(160)) % 256).astype(np.uint8)
    data = bytearray(cv2.imencode(".png", img)[1].tobytes())
    if damage == "truncate":
        data = data[: len(data) * 2 // 3]
    elif damage == "crc":
        data[60] ^= 0x10              # inside IDAT: its CRC no longer matches
    else:
        data = data[:-12]             # IEND chunk gone
    with pytest.raises(CorruptImageError, match="PNG"):
        decode_image(bytes(data), tmp_path / "x.png")
    np.testing.assert_array_equal(decode_image(cv2.imencode(".png", img)[1].tobytes(), "x.png", gray=True), img)


def test_survey_run_frame_is_decoded_strictly(tmp_path):
    from scenesig.surveys.run import read_run, write_run

    run, images = make_run(n_frames=4)
    write_run(run, tmp_path / "r", images=images)
    f = tmp_path / "r" / run.frame_files[2]
    f.write_bytes(f.read_bytes()[:-30])
    r = read_run(tmp_path / "r")               # headers only: reading the run still works
    with pytest.raises(CorruptImageError) as e:
        r.image(2)
    assert e.value.path == f and isinstance(e.value, DataError)
    assert r.image(1).shape == (48, 64, 3)


def test_data_errors_survive_pickling():
    """A DataError raised in a joblib / Dask worker reaches the driver as itself."""
    for exc in (DataError("a/b.csv", "bad", 3), CorruptImageError("x.jpg", "truncated"), OutputError("m/p", "full")):
        back = pickle.loads(pickle.dumps(exc))
        assert type(back) is type(exc) and str(back) == str(exc) and back.line == exc.line


# --------------------------------------------------------------------------------------- localise
@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from pipeline_world import make_live_run, make_map

    root = tmp_path_factory.mktemp("faults_world")
    run = make_live_run(root / "live", length_m=30.0)
    store = make_map(root / "map", length_m=50.0)
    return root, run, store


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])


def test_localise_skips_corrupt_frames_and_counts_them(world, tmp_path, caplog):
    from pipeline_world import TruthMethod

    from scenesig.localiser.replay import replay, write_outputs
    from scenesig.surveys.run import read_run

    root, run, store = world
    shutil.copytree(run.root, tmp_path / "live")
    for i in (4, 8):                                          # detector frames (every 4th)
        _truncate(tmp_path / "live" / run.frame_files[i])
    bad = read_run(tmp_path / "live")
    with caplog.at_level(logging.WARNING, logger="scenesig.localiser.replay"):
        res = replay(store, bad, TruthMethod(bad), every=4)
    m = write_outputs(res, store, tmp_path / "out", figure=False)
    assert m["frames_corrupt"] == 2 and m["corrupt_frames"] == [run.frame_files[4], run.frame_files[8]]
    assert sorted(res.corrupt) == [4, 8] and not res.detector_ran[[4, 8]].any()
    named = [r.getMessage() for r in caplog.records if "skipped frame" in r.getMessage()]
    assert len(named) == 2 and run.frame_files[4] in named[0]
    # odometry flowed: every frame has a pose, and the run still localised everywhere else
    assert len(res.times) == len(run) and m["failures"] == 0 and m["localisations"] == res.detector_ran.sum()
    assert np.linalg.norm(res.poses[8, :3, 3] - res.poses[7, :3, 3]) > 0.2
    from scenesig.experiments import read_localise_output, summary_rows
    from scenesig.report import _summary_table

    page = _summary_table(summary_rows([read_localise_output(tmp_path / "out")]), tmp_path)
    assert "corrupt frames" in page and "<td class='bad'>2</td>" in page


# --------------------------------------------------------------------------------------- build-map
def test_build_map_names_a_corrupt_frame_before_mining(tmp_path, capsys):
    from scenesig.cli import main as cli
    from scenesig.mapping.build import vet_images
    from scenesig.surveys.run import read_run, write_run

    run, images = make_run(n_frames=6)
    write_run(run, tmp_path / "r", images=images)
    bad_file = tmp_path / "r" / run.frame_files[3]
    _truncate(bad_file)
    r = read_run(tmp_path / "r")
    assert [[i for i, _ in b] for b in vet_images([r], jobs=2, progress=False)] == [[3]]
    assert len(r.without_frames([3])) == 5 and r.without_frames([3]).frame_files[3] == run.frame_files[4]
    rc = cli(["build-map", str(tmp_path / "r"), "--reference", str(tmp_path / "r"), "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err
    assert rc == 2 and f"scenesig: error: {bad_file}: " in err and "--skip-corrupt" in err
    assert "Traceback" not in err and not (tmp_path / "m" / "places").exists()


# --------------------------------------------------------------------------------------- scenesig check
def _run_check(paths, tmp_path, *extra):
    import argparse

    from scenesig.commands import check

    ap = argparse.ArgumentParser()
    check.register({"": ap.add_subparsers()})
    args = ap.parse_args(["check", *map(str, paths), "--json", str(tmp_path / "check.json"), *extra])
    return args._run(args), json.loads((tmp_path / "check.json").read_text())


def test_check_lists_every_problem_of_a_run(tmp_path, capsys):
    from scenesig.surveys.run import write_run

    run, images = make_run(n_frames=30)
    run.frame_times = run.frame_times.copy()
    run.frame_times[20:] += 2.0                     # a 2 s hole in the images
    write_run(run, tmp_path / "r", images=images)
    root = tmp_path / "r"
    rc, doc = _run_check([root], tmp_path)
    assert rc == 2 and doc["summary"]["errors"] == 1
    gap = doc["problems"][0]
    assert gap["file"] == str(root / "frames.csv") and gap["line"] == 22 and "gap of 2.050 s" in gap["reason"]
    _truncate(root / run.frame_files[5])
    (root / run.frame_files[9]).write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    lines = (root / "odometry.csv").read_text().splitlines()
    lines[4] = ",".join(lines[4].split(",")[:3] + ["nan"] + lines[4].split(",")[4:])
    (root / "odometry.csv").write_text("\n".join(lines) + "\n")
    rc, doc = _run_check([root], tmp_path)
    out = capsys.readouterr().out
    problems = {(Path(p["file"]).name, p["line"]) for p in doc["problems"] if p["severity"] == "error"}
    assert rc == 2 and problems == {("odometry.csv", 5), ("000005.png", None), ("000009.png", None),
                                    ("frames.csv", 22)}
    assert f"{root / 'odometry.csv'}:5: error: NaN or infinite value" in out
    assert "checked 1 runs (30 images) and 0 maps (0 places): 4 errors" in out
    # the timing problems -- rate and coverage -- are warnings
    meta = (root / "run.toml").read_text().replace("camera_hz = 20.0", "camera_hz = 10.0")
    (root / "run.toml").write_text(meta)
    rc, doc = _run_check([root], tmp_path, "--no-images")
    assert any("rates.camera_hz is 10 Hz" in p["reason"] and p["severity"] == "warning" for p in doc["problems"])


def test_check_maps_and_folders(tmp_path, capsys):
    from test_store import build

    from scenesig.surveys.run import write_run

    run, images = make_run(n_frames=8)
    write_run(run, tmp_path / "world" / "r1", images=images)
    write_run(run, tmp_path / "world" / "r2", images=images)
    build(tmp_path / "world" / "map")
    rc, doc = _run_check([tmp_path / "world"], tmp_path)
    assert rc == 0 and doc["summary"] == {"runs": 2, "maps": 1, "images_checked": 16, "places_checked": 5,
                                          "errors": 0, "warnings": 0}
    places = tmp_path / "world" / "map" / "places"
    raw = bytearray((places / "place_0001.npz").read_bytes())
    raw[100] ^= 1
    (places / "place_0001.npz").write_bytes(bytes(raw))
    (places / "place_0003.npz").unlink()
    rc, doc = _run_check([tmp_path / "world" / "map", tmp_path / "nowhere"], tmp_path)
    reasons = [(Path(p["file"]).name, p["reason"].split(":")[0]) for p in doc["problems"]]
    assert rc == 2 and reasons == [("nowhere", "not found"), ("place_0001.npz", "checksum mismatch"),
                                   ("place_0003.npz", "place 3's file listed in manifest.json is missing (No such file or directory)")]
    (tmp_path / "world" / "map" / "manifest.json").unlink()
    rc, doc = _run_check([tmp_path / "world" / "map"], tmp_path)
    assert rc == 2 and doc["problems"][0]["reason"].startswith("no manifest: not a finished scenesig map")
    (tmp_path / "world" / "map" / "journal.jsonl").write_text('{"header": {}}\n')
    rc, doc = _run_check([tmp_path / "world" / "map"], tmp_path)
    assert rc == 2 and "a build was interrupted here" in doc["problems"][0]["reason"]


# --------------------------------------------------------------------------------------- full disk
def _same_except_timings(a: dict, b: dict):
    from scenesig.localiser.replay import TIMING_KEYS

    assert sorted(a) == sorted(b)
    for name in a:
        if name == "metrics.json":
            ma, mb = json.loads(a[name]), json.loads(b[name])
            for k in TIMING_KEYS:
                ma.pop(k), mb.pop(k)
            assert ma == mb
        else:
            assert a[name] == b[name], name


@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EACCES])
def test_localise_on_a_full_disk_loses_nothing_and_reruns_to_the_same_bytes(world, tmp_path, monkeypatch, capsys,
                                                                            err):
    from scenesig.cli import main as cli

    root, run, store = world
    args = ["localise", str(store.root), str(run.root), "--every", "2", "--out"]
    assert cli(args + [str(tmp_path / "ref")]) == 0
    reference = folder_bytes(tmp_path / "ref")
    out = tmp_path / "out"
    shutil.copytree(tmp_path / "ref", out)                      # an earlier result in the folder
    # ENOSPC at once, or once the trajectory is written (in frames.csv); EACCES: nothing can be created
    for after in ((0, len(reference["trajectory.tum"]) + 100) if err == errno.ENOSPC else (0,)):
        with monkeypatch.context() as mp:
            if err == errno.ENOSPC:
                disk_full(mp, out, after_bytes=after)
            else:
                read_only(mp, out)
            capsys.readouterr()
            assert cli(args + [str(out)]) == 2
        msg = capsys.readouterr().err
        assert f"\nscenesig: error: {out}/" in "\n" + msg.split("\r")[-1] and "could not write" in msg
        assert "Traceback" not in msg
        # nothing half-written, nothing lost, no temp file (files written before the failure are this
        # run's, identical but for the timings)
        _same_except_timings(folder_bytes(out), reference)
    shutil.rmtree(out)
    with monkeypatch.context() as mp:
        # a fresh folder: the trajectory fits, the disk fills during frames.csv; what is there is whole
        disk_full(mp, out, after_bytes=len(reference["trajectory.tum"]) + 1000)
        assert cli(args + [str(out)]) == 2
    partial = folder_bytes(out)
    assert partial and set(partial) < set(reference)
    _same_except_timings(partial, {k: reference[k] for k in partial})
    assert cli(args + [str(out)]) == 0                        # space freed: the rerun completes
    _same_except_timings(folder_bytes(out), reference)


def test_a_figure_that_cannot_be_written_leaves_nothing(tmp_path):
    """Figures are written by their library (matplotlib) to a temporary name: an OSError there is an
    OutputError naming the figure, and neither the temporary nor the final file is left."""
    from scenesig.surveys.io import atomic_path

    (tmp_path / "fig.png").write_bytes(b"old figure")
    with pytest.raises(OutputError, match=r"fig\.png: could not write: No space left on device \(ENOSPC\)"):
        with atomic_path(tmp_path / "fig.png") as tmp:
            tmp.write_bytes(b"half a fig")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert folder_bytes(tmp_path) == {"fig.png": b"old figure"}


def test_report_on_a_full_disk_keeps_the_previous_page(world, tmp_path, monkeypatch):
    from pipeline_world import TruthMethod

    from scenesig.localiser.replay import replay, write_outputs
    from scenesig.report import build_report

    root, run, store = world
    write_outputs(replay(store, run, TruthMethod(run), every=4), store, tmp_path / "res" / "a")
    build_report([tmp_path / "res"], tmp_path / "rep")
    before = folder_bytes(tmp_path / "rep")
    with monkeypatch.context() as mp:
        disk_full(mp, tmp_path / "rep", after_bytes=200)
        with pytest.raises(OutputError, match="could not write"):
            build_report([tmp_path / "res"], tmp_path / "rep")
    after = folder_bytes(tmp_path / "rep")
    assert after["index.html"] == before["index.html"] and sorted(after) == sorted(before)
    for k, v in after.items():               # figures: the old or the new, each whole
        assert v[-12:] == b"\x00\x00\x00\x00IEND\xaeB`\x82" or not k.endswith(".png")
    build_report([tmp_path / "res"], tmp_path / "rep")

    def strip(page):    # the generation time and duration are the only lines that change
        return [ln for ln in page.decode().splitlines() if "generated" not in ln and "built in" not in ln]
    again = folder_bytes(tmp_path / "rep")
    assert strip(again.pop("index.html")) == strip(before.pop("index.html")) and again == before


def test_map_writer_on_a_full_disk_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    from test_store import CAM, N_PLACES, PARAMS, T_VC, build, make_place, places_meta

    from scenesig.mapping.store import JOURNAL, MapWriter

    reference = folder_bytes(build(tmp_path / "ref"))
    root = tmp_path / "m"
    w = MapWriter(root, CAM, T_VC, PARAMS)
    w.write_place(0, make_place(0))
    first_id = w.map_id
    size1 = len(reference["places/place_0001.npz"])
    for after in (100, size1 + 20):          # inside the place file; inside its journal line
        with monkeypatch.context() as mp:
            disk_full(mp, root, after_bytes=after)
            with pytest.raises(OutputError, match="No space left on device"):
                w.write_place(1, make_place(1))
        assert not list(root.rglob("*.tmp")) and not list(root.rglob(".*tmp"))
        journal = (root / JOURNAL).read_text().splitlines()
        assert all(json.loads(line) for line in journal)          # no torn line
    with monkeypatch.context() as mp:
        read_only(mp, root)
        with pytest.raises(OutputError, match="Permission denied"):
            MapWriter(root, CAM, T_VC, PARAMS)
    w = MapWriter(root, CAM, T_VC, PARAMS)   # rerun after freeing space
    for i in range(N_PLACES):
        if not w.has_place(i):
            w.write_place(i, make_place(i))
    w.finalise(places_meta())
    got = folder_bytes(root)
    # the same bytes but for the identity each map drew; the resumed build kept its own (the journal's)
    ma, mb = json.loads(got.pop("manifest.json")), json.loads(reference.pop("manifest.json"))
    assert ma.pop("map_id") == first_id != mb.pop("map_id") and ma == mb
    assert got == reference


# --------------------------------------------------------------------------------------- real time under load
def _hog(seconds):
    end = time.perf_counter() + seconds
    x = 0
    while time.perf_counter() < end:
        x += 1


def test_realtime_keeps_up_with_both_cores_loaded(world, tmp_path, monkeypatch):
    """Two CPU hogs (bounded: they stop on their own) and an odometry update that costs more CPU than
    the odometry rate allows: the replay still ends on time, the odometry backlog stays bounded by
    composing late samples, stale frames are dropped, and it still localises."""
    from pipeline_world import TruthMethod

    from scenesig.localiser import pipeline
    from scenesig.localiser.replay import replay, write_outputs

    root, run, store = world
    original = pipeline.Localiser.add_odometry

    def slow_odometry(self, t, inc):          # 80 ms of CPU per sample: 1.6 s per second of 20 Hz data
        _hog(0.08)
        original(self, t, inc)

    monkeypatch.setattr(pipeline.Localiser, "add_odometry", slow_odometry)
    duration = float(run.frame_times[-1] - run.frame_times[0])
    ctx = multiprocessing.get_context("spawn")
    hogs = [ctx.Process(target=_hog, args=(duration + 5.0,), daemon=True) for _ in range(2)]
    for h in hogs:
        h.start()
    try:
        t0 = time.perf_counter()
        res = replay(store, run, TruthMethod(run), realtime=True, speed=1.0,
                     config={"odometry_queue": 4})
        wall = time.perf_counter() - t0
    finally:
        for h in hogs:
            h.terminate()
            h.join()
    m = write_outputs(res, store, tmp_path / "rt", figure=False)
    assert wall < duration + 2.0, f"fell behind: {wall:.1f} s for {duration:.1f} s of data"
    assert m["odometry_coalesced"] > 0 and m["lag_max_s"] < 1.5
    # every frame was either dropped as stale or detected and solved
    assert m["frames_dropped"] > 0 and m["frames_dropped"] + m["detector_frames"] == len(run)
    assert m["failures"] == 0 and m["localisations"] > 0
    # composing increments is exact: the dead-reckoned end pose matches the odometry's
    assert m["lateral_error_m"]["median"] < 0.5


# --------------------------------------------------------------------------------------- heavy: real builds
@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory):
    pytest.importorskip("scenesig.surveys.sim.simulate")
    from build_world import tiny_map, tiny_runs

    base = tmp_path_factory.getbasetemp()
    return tiny_runs(base), tiny_map(base)


@pytest.mark.heavy
def test_build_map_skip_corrupt_leaves_the_frames_out(tiny_world, tmp_path):
    from build_world import CONFIG

    from scenesig.mapping.build import build_map
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.run import read_run

    runs, _ = tiny_world
    for r in runs:
        shutil.copytree(r.root, tmp_path / "runs" / r.root.name)
    night = tmp_path / "runs" / runs[2].root.name
    bad = [runs[2].frame_files[i] for i in (3, 10)]
    for f in bad:
        _truncate(night / f)
    copies = [read_run(tmp_path / "runs" / r.root.name) for r in runs]
    with pytest.raises(CorruptImageError, match="and 1 more corrupt frames"):
        build_map(copies, copies[0], tmp_path / "m", jobs=2, progress=False, config=CONFIG)
    summary = build_map(copies, copies[0], tmp_path / "m", jobs=2, progress=False, config=CONFIG, skip_corrupt=True)
    assert summary["frames_corrupt"] == 2 and summary["corrupt_frames"] == [str(night / f) for f in bad]
    on_disk = json.loads((tmp_path / "m" / "build_summary.json").read_text())
    assert on_disk["frames_corrupt"] == 2
    store = MapStore.open(tmp_path / "m", verify=True)
    assert store.params["frames_left_out"] == {copies[2].name: bad}
    assert all(m.signatures > 0 for m in store.places.values())


@pytest.mark.heavy
def test_build_map_on_a_full_disk_resumes_to_the_same_bytes(tiny_world, tmp_path, monkeypatch, capsys):
    from build_world import CONFIG, map_contents

    from scenesig.cli import main as cli

    runs, reference = tiny_world
    out = tmp_path / "m"
    args = ["build-map", *[str(r.root) for r in runs], "--reference", str(runs[0].root), "--out", str(out),
            "--config", json.dumps(CONFIG), "--jobs", "2"]
    first_place = len((reference / "places" / "place_0000.npz").read_bytes())
    with monkeypatch.context() as mp:
        disk_full(mp, out, after_bytes=first_place + 20_000)     # the first place fits, the second does not
        assert cli(args) == 2
    err = capsys.readouterr().err
    assert "scenesig: error: " in err and "No space left on device" in err and "Traceback" not in err
    assert not list(out.rglob("*.tmp")) and not (out / "manifest.json").exists()
    assert 1 <= len(list((out / "places").glob("place_*.npz"))) < len(list((reference / "places").glob("*.npz")))
    assert cli(args) == 0                                         # space freed: resumes
    a, b = map_contents(reference), map_contents(out)
    assert a == b
