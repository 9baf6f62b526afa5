"""Map building (mapping/build.py) on the simulated tiny world: the same map bytes from a local joblib
build, a Dask build, a build interrupted by ``places_subset`` and resumed, and a build killed with
SIGKILL and re-run; the summary's schema; and float16 filters that detect like the originals."""
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from build_world import CONFIG, map_contents

pytest.importorskip("scenesig.surveys.sim.simulate")

ROOT = Path(__file__).resolve().parents[1]


def _assert_same_map(a: dict, b: dict, what: str):
    assert sorted(a) == sorted(b), f"{what}: different files {sorted(set(a) ^ set(b))}"
    for name in a:
        assert a[name] == b[name], f"{what}: {name} differs"


def test_dask_and_resumed_builds_give_the_local_build_bytes(tiny_world, tmp_path):
    distributed = pytest.importorskip("distributed")
    from scenesig.mapping.build import build_map

    runs, local = tiny_world
    reference = map_contents(local)
    assert len(reference) >= 3 + 2  # three places, manifest, summary

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster, distributed.Client(cluster) as client:
        build_map(runs, runs[0], tmp_path / "dask", scheduler=client, progress=False, config=CONFIG)
    _assert_same_map(reference, map_contents(tmp_path / "dask"), "dask build")

    # interrupted: one place only, then the rest
    part = build_map(runs, runs[0], tmp_path / "resumed", jobs=1, progress=False, config=CONFIG,
                     places_subset=[1])
    assert part == {"partial": True, "built": [1]}
    assert not (tmp_path / "resumed" / "manifest.json").exists()
    first = (tmp_path / "resumed" / "places" / "place_0001.npz").stat().st_mtime_ns
    build_map(runs, runs[0], tmp_path / "resumed", jobs=1, progress=False, config=CONFIG)
    assert (tmp_path / "resumed" / "places" / "place_0001.npz").stat().st_mtime_ns == first  # not rebuilt
    _assert_same_map(reference, map_contents(tmp_path / "resumed"), "resumed build")


def test_killed_build_resumes_to_the_same_bytes(tiny_world, tmp_path):
    runs, local = tiny_world
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "scenesig", "build-map", *[str(r.root) for r in runs], "--reference", str(runs[0].root),
           "--out", str(out), "--jobs", "1", "--config", json.dumps(CONFIG)]
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    try:
        while not list((out / "places").glob("place_*.npz")):
            if proc.poll() is not None:
                pytest.fail(f"build exited ({proc.returncode}) before writing a place: {proc.stderr.read()[-2000:]}")
            if time.monotonic() > deadline:
                pytest.fail("no place file within 240 s")
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "manifest.json").exists(), "the build finished before it could be killed"
    written = sorted(p.name for p in (out / "places").glob("place_*.npz"))
    assert 1 <= len(written) < 3
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    _assert_same_map(map_contents(local), map_contents(out), "killed and re-run build")
    assert not (out / "journal.jsonl").exists()


def test_build_stopped_right_after_a_place_file_keeps_its_stats(tiny_world, tmp_path, monkeypatch):
    """The deterministic form of the SIGKILL race above: the build dies just after a place's file is
    written.  The re-run skips that place, so its stats must already be on disk -- the summary must
    be the uninterrupted build's."""
    from scenesig.mapping import store as store_mod
    from scenesig.mapping.build import build_map

    runs, local = tiny_world
    original = store_mod.MapWriter.write_place

    def write_then_die(self, index, data):
        original(self, index, data)
        raise KeyboardInterrupt("killed after writing a place")

    monkeypatch.setattr(store_mod.MapWriter, "write_place", write_then_die)
    with pytest.raises(KeyboardInterrupt):
        build_map(runs, runs[0], tmp_path / "m", jobs=1, progress=False, config=CONFIG)
    monkeypatch.setattr(store_mod.MapWriter, "write_place", original)
    assert len(list((tmp_path / "m" / "places").glob("place_*.npz"))) == 1
    build_map(runs, runs[0], tmp_path / "m", jobs=1, progress=False, config=CONFIG)
    _assert_same_map(map_contents(local), map_contents(tmp_path / "m"), "build stopped after a place file")


def test_build_summary_schema_and_values(tiny_world):
    runs, local = tiny_world
    summary = json.loads((local / "build_summary.json").read_text())
    for key in ("places", "signatures_per_place_mean", "bytes_per_place_mean", "seconds_per_place_mean",
                "landmark_depth_rel_error_median", "rejected"):
        assert key in summary, key
    manifest = json.loads((local / "manifest.json").read_text())
    assert summary["places"] == len(manifest["places"]) == 3
    sizes = [(local / p["file"]).stat().st_size for p in manifest["places"]]
    assert summary["bytes_per_place_mean"] == pytest.approx(np.mean(sizes))
    # the split by part accounts for the whole file (all but the zip's 22-byte end record)
    parts = summary["bytes_per_place_by_part_mean"]
    assert set(parts) == {"signatures", "point_features", "keyframe", "meta"}
    assert all(v > 0 for v in parts.values())
    assert sum(parts.values()) == pytest.approx(np.mean(sizes), abs=100)
    # ... and by map layer: the layers asked for (ORB, reference and every run's keyframe), their bytes and
    # build seconds; the point layers' bytes add up to the point-feature part
    assert summary["layers"] == ["signatures", "orb", "orb-all"]
    by_layer = summary["bytes_per_place_by_layer_mean"]
    assert set(by_layer) == {"signatures", "orb", "orb-all", "all_keyframe_poses", "keyframe", "meta"}
    assert by_layer["signatures"] == pytest.approx(parts["signatures"])
    assert by_layer["orb"] + by_layer["orb-all"] + by_layer["all_keyframe_poses"] == pytest.approx(
        parts["point_features"])
    secs = summary["seconds_per_place_by_layer_mean"]
    assert set(secs) == {"signatures", "orb", "orb-all"} and all(v > 0 for v in secs.values())
    assert sum(secs.values()) <= summary["seconds_per_place_mean"] * 1.001
    assert [p["bytes"] for p in manifest["places"]] == sizes
    assert summary["signatures_per_place_mean"] == pytest.approx(np.mean([p["signatures"] for p in manifest["places"]]))
    assert summary["signatures_per_place_mean"] > 0
    assert summary["seconds_per_place_mean"] > 0
    rejected = summary["rejected"]
    assert {"not_converged", "temporal", "depth"} <= set(rejected)
    assert all(isinstance(v, int) and v >= 0 for v in rejected.values())
    assert sum(rejected.values()) > 0
    # simulated runs: the depth error against the renderer's depth buffer is measured
    assert summary["landmarks_with_truth"] > 0
    err = summary["landmark_depth_rel_error_median"]
    assert isinstance(err, float) and 0 <= err < 1.0
    q = summary["landmark_depth_rel_error_quartiles"]
    assert q[0] <= q[1] <= q[2] and q[1] == pytest.approx(err)
    # one per-place stats line per place, surviving for resumed builds
    lines = [json.loads(s) for s in (local / "build_stats.jsonl").read_text().splitlines()]
    assert sorted(s["place"] for s in lines) == [0, 1, 2]


def test_stored_filters_detect_like_the_originals(tiny_world):
    """The store keeps bank filters as float16 with fewer mantissa bits where the row error allows it:
    every detection over the place's window frames must stay where it was, at the same level."""
    from scenesig.mapping import places as places_mod
    from scenesig.mapping.build import build_place
    from scenesig.mapping.store import decode_place, encode_place
    from scenesig.signatures.bank import Bank

    runs, local = tiny_world
    ref = runs[0]
    place = places_mod.define_places(ref, CONFIG["places"])[1]
    views = places_mod.training_views(place, runs, CONFIG["places"])
    views = [v for v in views if v.run.name == ref.name] + [v for v in views if v.run.name != ref.name]
    data, _ = build_place(place, views, [], CONFIG)  # no place 1 +- 3: no extra negatives, as in build_map
    raw = encode_place(1, data)
    # the same bytes as the map's own file (the build is deterministic)
    assert raw == (local / "places" / "place_0001.npz").read_bytes()
    fmt = json.loads(np.load(io.BytesIO(raw))["format"].tobytes())
    assert 4 <= fmt["float16_planes"]["bank/weights"]["mantissa_bits"] < 10
    original = Bank.from_arrays(data.bank_arrays)
    stored = Bank.from_arrays(decode_place(raw, Path("place_0001.npz"), 1).bank_arrays)
    assert len(original) == len(stored) > 0
    w0 = np.concatenate([c.weights.ravel() for c in original.classifiers])
    w1 = np.concatenate([c.weights.ravel() for c in stored.classifiers])
    assert not np.array_equal(w0, w1)  # really rounded ...
    n = 0
    for j in views[0].window:
        img = ref.image(int(j), gray=True)
        a, b = original.detect(img), stored.detect(img)
        ok = np.isfinite(a.x[:, 0])
        np.testing.assert_array_equal(np.isfinite(b.x[:, 0]), ok)
        # ... yet every firing is where it was (sub-pixel), at the same level, with the same probability
        assert np.abs(a.x[ok] - b.x[ok]).max(initial=0) < 0.25
        assert np.abs(a.y[ok] - b.y[ok]).max(initial=0) < 0.25
        np.testing.assert_array_equal(a.level[ok], b.level[ok])
        assert np.abs(a.prob[ok] - b.prob[ok]).max(initial=0) < 0.01
        n += int(ok.sum())
    assert n >= 5 * len(original)
