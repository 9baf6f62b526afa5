"""Lifelong map updates (mapping/update.py) on the tiny world: only weak places change, a SIGKILL mid-update
leaves a valid map and a re-run finishes it to the same bytes, a concurrent reader never fails, and a
localisation that failed everywhere adds nothing and says why."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from build_world import tiny_map, tiny_runs  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The tiny map and a localisation of its night run against it."""
    from scenesig.localiser.replay import localise

    base = tmp_path_factory.getbasetemp()
    runs = tiny_runs(base)
    root = tiny_map(base)
    night = next(r for r in runs if r.conditions[0] == "night")
    loc = base / "loc_night"
    if not (loc / "metrics.json").exists():
        localise(root, night.root, loc, progress=False, figure=False)
    return root, loc


def _contents(root: Path) -> dict:
    """The map as a reader sees it: the manifest and the place files it lists (bytes)."""
    doc = json.loads((root / "manifest.json").read_text())
    return {"manifest.json": (root / "manifest.json").read_bytes(),
            **{p["file"]: (root / p["file"]).read_bytes() for p in doc["places"]}}


@pytest.fixture(scope="module")
def reference_update(world, tmp_path_factory):
    """An uninterrupted update of the tiny map with the night localisation, into a new folder."""
    from scenesig.mapping.update import read_localisation, update_map

    root, loc = world
    out = tmp_path_factory.mktemp("updated") / "map"
    summary = update_map(root, [read_localisation(loc)], out=out, progress=False)
    return out, summary


def test_metrics_gain_detection_rates(world):
    from scenesig.localiser.outputs import read_frames_csv

    _, loc = world
    m = json.loads((loc / "metrics.json").read_text())
    fr = read_frames_csv(loc / "frames.csv")
    assert m["inliers_per_detection_mean"] == pytest.approx(fr["inliers"].sum() / fr["detections"].sum())
    assert m["detections_per_frame_mean"] == pytest.approx(fr["detections"].sum() / m["detector_frames"])
    assert Path(m["run_path"]).is_dir()


def test_update_changes_only_the_weak_places(world, reference_update):
    from scenesig.mapping.show import describe_map
    from scenesig.mapping.store import MapStore

    root, loc = world
    out, summary = reference_update
    verdict = summary["verdicts"][str(loc)]
    weak = sorted(i for i, r in verdict.items() if r["weak"] and r["frame"] is not None)
    assert weak and summary["updated"] == weak
    assert any(not r["weak"] for r in verdict.values()), "the rule must keep a well-localised place"
    old = MapStore.open(root)
    new = MapStore.open(out, verify=True)
    assert (old.generation, new.generation) == (0, 1)
    for i, m in new.places.items():
        before = (root / old.places[i].file).read_bytes()
        after = (out / m.file).read_bytes()
        if i in weak:
            assert m.file.endswith(".g0001.npz")
            exp = m.extra["experiences"]
            assert [(e["run"], e["generation"], e["frame"]) for e in exp] == \
                [(json.loads((loc / "metrics.json").read_text())["run"], 1, verdict[i]["frame"])]
            d_old, d_new = old.load_place(i), new.load_place(i)
            k = len(d_old.landmarks)
            # kept classifiers keep their landmarks (refined depths) and ids; new ones are appended
            np.testing.assert_allclose(d_new.landmarks[:k], d_old.landmarks, rtol=1e-6, atol=1e-6)
            assert d_new.classifier_ids[:k].tolist() == d_old.classifier_ids.tolist()
            assert len(d_new.landmarks) == k + exp[0]["signatures_added"]
        else:
            assert m.file == old.places[i].file and after == before, f"place {i} is not weak but changed"
    text = describe_map(out)
    assert "generation 1" in text and "experience" in text
    # the original map is untouched by an update with --out
    assert MapStore.open(root, verify=True).generation == 0


def _update_process(root: Path, loc: Path, pause_s: float = 0.0) -> subprocess.Popen:
    """``update_map`` in its own process; ``pause_s`` after each journalled place, so a kill lands between
    places however fast the machine is (a tiny map's update can otherwise finish between two polls)."""
    code = ("import sys, time; from scenesig.mapping.update import read_localisation; "
            "import scenesig.mapping.update as U; real = U._append; "
            f"U._append = lambda p, o: (real(p, o), time.sleep({float(pause_s)})); "
            "U.update_map(sys.argv[1], [read_localisation(sys.argv[2])], progress=False)")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-c", code, str(root), str(loc)], env=env, cwd=ROOT)


@pytest.fixture(scope="module")
def killed_and_resumed(world, reference_update, tmp_path_factory):
    """An in-place update SIGKILLed after its first place file, then re-run, while a reader loads places."""
    from scenesig.mapping.store import MapStore

    root, loc = world
    work = tmp_path_factory.mktemp("inplace") / "map"
    shutil.copytree(root, work)
    record = {"loads": 0, "errors": [], "generations": set()}
    stop = threading.Event()
    opened = MapStore.open(work, cache_size=0)    # a long-lived reader: opened before the update

    def reader():
        while not stop.is_set():
            try:
                for store in (opened, MapStore.open(work, cache_size=0)):
                    for i in store.places:
                        store.load_place(i)
                        record["loads"] += 1
                    record["generations"].add(store.generation)
            except Exception as exc:  # noqa: BLE001 -- any failure to load is what the test looks for
                record["errors"].append(repr(exc))

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    proc = _update_process(work, loc, pause_s=5.0)
    journal = work / "update.jsonl"
    deadline = time.time() + 600
    while proc.poll() is None and time.time() < deadline:
        if journal.exists() and len(journal.read_text().splitlines()) >= 2:  # header + one place
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.05)
    proc.wait()
    record["killed"] = proc.returncode == -signal.SIGKILL
    valid = MapStore.open(work, verify=True)     # the map is valid after the kill
    record["generation_after_kill"] = valid.generation
    resumed = _update_process(work, loc)
    resumed.wait()
    stop.set()
    t.join()
    record["resume_rc"] = resumed.returncode
    return work, record


def test_kill_and_resume_gives_the_same_bytes(reference_update, killed_and_resumed):
    out, _ = reference_update
    work, record = killed_and_resumed
    assert record["killed"], "the update finished before it could be killed"
    assert record["generation_after_kill"] == 0
    assert record["resume_rc"] == 0
    assert _contents(work) == _contents(out)
    assert not (work / "update.jsonl").exists()


def test_concurrent_reader_never_fails(killed_and_resumed):
    _, record = killed_and_resumed
    assert record["errors"] == []
    assert record["loads"] > 0 and 1 in record["generations"]


def test_update_from_a_failed_localisation_adds_nothing(world, tmp_path, capsys):
    from scenesig.cli import main

    root, loc = world
    failed = tmp_path / "failed"
    shutil.copytree(loc, failed)
    lines = (failed / "frames.csv").read_text().splitlines()
    head = lines[0].split(",")
    rows = [r.split(",") for r in lines[1:]]
    for r in rows:  # the localiser accepted nothing anywhere
        r[head.index("localised")] = "0"
        r[head.index("inliers")] = "0"
    (failed / "frames.csv").write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    before = _contents(root)
    assert main(["map", "update", str(root), str(failed)]) == 0
    out = capsys.readouterr().out
    assert "nothing added" in out and "never localised" in out
    assert _contents(root) == before


@pytest.mark.parametrize("after_bytes", [0, 30000])
def test_update_on_a_full_disk_keeps_the_old_map_and_reruns_to_the_same_bytes(world, reference_update, tmp_path,
                                                                             monkeypatch, capsys, after_bytes):
    """ENOSPC at once or part-way through a place file: exit 2 naming the file, the map a reader sees is the
    old generation, and the update re-run once space is freed ends with the uninterrupted update's bytes."""
    from faultinject import disk_full

    from scenesig.cli import main

    root, loc = world
    out, _ = reference_update
    work = tmp_path / "map"
    shutil.copytree(root, work)
    before = _contents(work)
    with monkeypatch.context() as mp:
        state = disk_full(mp, work, after_bytes=after_bytes)
        assert main(["map", "update", str(work), str(loc)]) == 2
    assert state["failures"] >= 1
    err = capsys.readouterr().err
    assert f"scenesig: error: {work}/" in err and "could not write" in err and "Traceback" not in err
    assert _contents(work) == before                          # readers still see the old map, whole
    assert not [p for p in work.rglob("*") if ".tmp" in p.name]
    assert main(["map", "update", str(work), str(loc)]) == 0
    assert _contents(work) == _contents(out)


def test_live_pose_covariance_grows_with_blind_distance_and_lever_arm():
    """New landmarks carry the live pose's uncertainty: more with odometry from the fix, more far away."""
    from scenesig.mapping.update import _live_pose_covariance, default_config

    T = np.eye(4)
    T[:2, 3] = [1.0, 2.0]
    pts = np.array([[6.0, 2.0, 1.0], [21.0, 2.0, 1.0]])   # 5 m and 20 m ahead of the vehicle
    near = _live_pose_covariance(pts, T, 0.0, default_config)
    far = _live_pose_covariance(pts, T, 10.0, default_config)
    s = default_config["live_pose_sigma_m"]
    assert np.allclose(near[0, 0, 0], s * s)                 # straight ahead: yaw moves it sideways only
    assert near[1, 1, 1] > near[0, 1, 1] > s * s              # the yaw term grows with the lever arm
    assert np.all(far[:, 0, 0] > near[:, 0, 0])
    assert np.all(np.linalg.eigvalsh(near) > 0)


def test_align_to_reference_recovers_a_planar_pose_error():
    """The live pose is corrected from where the new classifiers fire in the reference frames (whose
    pose in the place frame is exact); with too few firings it is left as it was."""
    from scenesig.mapping.places import TrainingView
    from scenesig.mapping.update import _planar, align_to_reference
    from scenesig.surveys.geometry import Camera, invert

    camera = Camera(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)
    T_vc = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1.5], [0, 0, 0, 1.0]])   # x forward, camera z
    rng = np.random.default_rng(3)
    pts_place = np.stack([rng.uniform(8, 25, 30), rng.uniform(-6, 6, 30), rng.uniform(0.2, 4, 30)], axis=1)
    T_pv_true = np.eye(4)
    T_pv_true[:2, 3] = [1.0, 0.3]
    landmarks_vehicle = (pts_place - T_pv_true[:3, 3]) @ T_pv_true[:3, :3]         # in the live vehicle frame
    error = _planar([0.4, -0.35, np.radians(1.5)], T_pv_true[:2, 3])
    T_pv_est = error @ T_pv_true
    window = np.arange(5)
    T_frame_window = np.stack([np.eye(4)] * 5)
    T_frame_window[:, 0, 3] = [-4.0, -2.0, 0.0, 2.0, 4.0]

    class _Run:
        def __init__(self):
            self.camera, self.T_vehicle_camera = camera, T_vc

        def image(self, frame, gray=True):
            return int(frame)

    class _Det:
        pass

    class _Bank:
        """Fires exactly at the true landmarks' pixels (within the search windows)."""

        def detect(self, frame, windows=None, top_n=1):
            T_cam_place = invert(T_frame_window[frame] @ T_vc)
            uv, _ = camera.project(pts_place[:len(windows)] @ T_cam_place[:3, :3].T + T_cam_place[:3, 3])
            inside = (uv[:, 0] >= windows[:, 0]) & (uv[:, 0] <= windows[:, 2]) & \
                     (uv[:, 1] >= windows[:, 1]) & (uv[:, 1] <= windows[:, 3])
            d = _Det()
            d.x = np.where(inside, uv[:, 0], np.nan)[:, None]
            d.y = np.where(inside, uv[:, 1], np.nan)[:, None]
            d.prob = np.where(inside, 0.9, np.nan)[:, None]
            return d

    view = TrainingView(_Run(), 2, window, T_frame_window, 0.0)
    T, info = align_to_reference(_Bank(), landmarks_vehicle, T_pv_est, view)
    assert info["used"] and info["inliers"] >= 8
    assert np.abs(T[:3, 3] - T_pv_true[:3, 3]).max() < 0.02
    assert abs(np.degrees(np.arctan2(T[1, 0], T[0, 0]))) < 0.05
    T2, info2 = align_to_reference(_Bank(), landmarks_vehicle[:3], T_pv_est, view)   # too few firings
    assert not info2["used"] and np.array_equal(T2, T_pv_est)
