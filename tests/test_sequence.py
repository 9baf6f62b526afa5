"""Real sequences in: ``scenesig import images`` (an ordered image folder as a survey run without odometry) and
``scenesig bench sequence`` (odometry-free sequence place recognition, recall@1 within +-tolerance frames)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from scenesig.surveys.errors import DataError
from scenesig.surveys.importers.image_folder import import_image_folder, natural_key
from scenesig.surveys.run import read_run


def _texture(seed: int, size=(128, 96)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 255, (size[1] // 8, size[0] // 8, 3), dtype=np.uint8), size,
                     interpolation=cv2.INTER_CUBIC)
    return img


def _folder(path: Path, n: int, names=None, darker: float = 1.0, noise: int = 0, ext=".png", seed0=0) -> Path:
    """An ordered folder: image k shows place k (a texture of its own); the query is darker and noisy."""
    path.mkdir(parents=True)
    rng = np.random.default_rng(99)
    for k in range(n):
        img = _texture(seed0 + k).astype(float) * darker
        if noise:
            img += rng.normal(0, noise, img.shape)
        name = names[k] if names else f"frame{k}{ext}"
        cv2.imwrite(str(path / name), np.clip(img, 0, 255).astype(np.uint8))
    return path


def _cli(argv):
    from scenesig import cli

    return cli.main(argv)


def test_natural_order_times_and_what_an_image_folder_lacks(tmp_path, capsys):
    src = _folder(tmp_path / "seq", 12)                     # frame0 .. frame11: frame10 after frame9
    (src / "displacements.txt").write_text("0 0\n")
    assert _cli(["import", "images", str(src), "--hz", "4", "--out", str(tmp_path / "run")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 12 and summary["ignored_files"] == 1 and summary["odometry_source"] == "none"
    run = read_run(tmp_path / "run")
    assert run.frame_files == [f"images/frame{k}.png" for k in range(12)]
    assert np.allclose(run.frame_times, np.arange(12) / 4.0)
    assert run.odometry_source == "none" and np.allclose(run.odometry_poses, np.eye(4))
    assert run.metadata["camera"].startswith("assumed") and run.camera.size == (128, 96)
    assert np.isclose(run.camera.fx, 64 / np.tan(np.radians(30)))
    # the pixels are the source file's, bit for bit
    assert (tmp_path / "run/images/frame3.png").read_bytes() == (src / "frame3.png").read_bytes()
    assert run.groundtruth_times is None and run.gps is None
    assert sorted(["img10.jpg", "img2.jpg", "IMG1.jpg"], key=natural_key) == ["IMG1.jpg", "img2.jpg", "img10.jpg"]


def test_bad_images_are_named(tmp_path, capsys):
    src = _folder(tmp_path / "seq", 4, ext=".jpg")
    data = (src / "frame2.jpg").read_bytes()
    (src / "frame2.jpg").write_bytes(data[: len(data) // 2])          # truncated
    assert _cli(["import", "images", str(src), "--hz", "1", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "frame2.jpg" in err and "scenesig: error:" in err
    assert not (tmp_path / "run").exists()                               # nothing half-written
    (src / "frame2.jpg").write_bytes(data)
    cv2.imwrite(str(src / "frame3.jpg"), np.zeros((50, 60, 3), np.uint8))
    with pytest.raises(DataError, match=r"frame3\.jpg: image is 60x50 but the folder's first image"):
        import_image_folder(src, tmp_path / "run2", {"hz": 1})
    with pytest.raises(DataError, match="no image files"):
        import_image_folder(_empty(tmp_path / "empty"), tmp_path / "run3", {"hz": 1})
    with pytest.raises(DataError, match="image folder not found"):
        import_image_folder(tmp_path / "missing", tmp_path / "run5", {"hz": 1})
    with pytest.raises(ValueError, match="hz"):
        import_image_folder(src, tmp_path / "run4", {"hz": 0})


def _empty(path: Path) -> Path:
    path.mkdir()
    (path / "readme.txt").write_text("no frames")
    return path


def test_positions_and_alignment(tmp_path):
    a = _folder(tmp_path / "a", 5)
    b = _folder(tmp_path / "b", 5, darker=0.5)
    pos = tmp_path / "pos.csv"
    pos.write_text("frame,x,y\n" + "".join(f"{k},{2.0 * k},{1.0}\n" for k in range(5)))
    ra = read_run(import_image_folder(a, tmp_path / "ra", {"hz": 2, "positions": pos}, progress=False))
    assert np.allclose(ra.gps[:, 1:], [[2.0 * k, 1.0, 0.0] for k in range(5)])
    assert np.allclose(ra.groundtruth_poses[:, :3, 3], ra.gps[:, 1:])
    assert np.allclose(ra.groundtruth_poses[:, :3, :3], np.eye(3))       # heading along +x
    rb = read_run(import_image_folder(b, tmp_path / "rb", {"hz": 2, "aligned_with": tmp_path / "ra"},
                                      progress=False))
    assert rb.metadata["aligned_with"] == str((tmp_path / "ra").resolve()) and rb.gps is None
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,x,y\n0,1,2\n7,1,2\n")
    with pytest.raises(DataError, match=r"bad\.csv:3: frame '7' is not an index"):
        import_image_folder(a, tmp_path / "rc", {"hz": 2, "positions": bad})
    short = _folder(tmp_path / "short", 3)
    with pytest.raises(DataError, match="has 5 frames but .* has 3"):
        import_image_folder(short, tmp_path / "rd", {"hz": 2, "aligned_with": tmp_path / "ra"})


@pytest.fixture
def traverses(tmp_path):
    """A reference, a second map traverse and a darker, noisy query of 14 places, frame-aligned."""
    ref = import_image_folder(_folder(tmp_path / "ref", 14), tmp_path / "r_ref", {"hz": 1}, progress=False)
    m2 = import_image_folder(_folder(tmp_path / "m2", 14, darker=0.8, noise=8), tmp_path / "r_m2",
                             {"hz": 1, "aligned_with": ref}, progress=False)
    q = import_image_folder(_folder(tmp_path / "q", 14, darker=0.6, noise=12), tmp_path / "r_q",
                            {"hz": 1, "aligned_with": ref}, progress=False)
    return ref, m2, q


def test_bench_sequence_scores_methods_on_aligned_traverses(traverses, tmp_path, capsys):
    ref, m2, q = traverses
    out = tmp_path / "seq.json"
    rc = _cli(["bench", "sequence", str(ref), str(m2), "--query", str(q), "--tolerance", "0",
               "--methods", "hog,seqslam", "--json", str(out)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames"] == doc["places"] == 14 and doc["truth"] == "frame alignment" and doc["tolerance"] == 0
    assert set(doc["methods"]) == {"hog", "seqslam"}
    for m in doc["methods"].values():
        assert set(m) >= {"recall_at_1", "precision_at_100_recall", "recall_at_100_precision", "cpu_ms_per_frame"}
        assert m["cpu_ms_per_frame"] > 0 and m["precision_at_100_recall"] == m["recall_at_1"]
    assert doc["methods"]["hog"]["recall_at_1"] == 1.0           # distinct textures: the right place every time
    full = json.loads(out.read_text())
    assert full["matches"]["hog"] == list(range(14)) and full["truth_frames"] == list(range(14))


@pytest.mark.heavy
def test_bench_sequence_signature_methods(traverses):
    """signatures and signatures-seq mine one bank per reference frame from the map traverses and verify."""
    from scenesig.benchmarks.sequence import run_benchmark

    ref, m2, q = traverses
    doc = run_benchmark([ref, m2], q, ["signatures", "signatures-seq"], tolerance=1, progress=False,
                        config={"shortlist": 4})
    for name in ("signatures", "signatures-seq"):
        assert doc["methods"][name]["recall_at_1"] >= 0.5, doc
        assert doc["methods"][name]["shortlist"] == 4
    assert doc["methods"]["signatures"]["seconds_map"] > 0


def test_bench_sequence_truth_from_positions_or_an_error(tmp_path, capsys):
    from scenesig.benchmarks.sequence import precision_recall, run_benchmark

    pr = tmp_path / "pr.csv"
    pr.write_text("frame,x,y\n" + "".join(f"{k},{5.0 * k},0\n" for k in range(8)))
    pq = tmp_path / "pq.csv"                     # the query starts two places in, at 2.5 m spacing
    pq.write_text("frame,x,y\n" + "".join(f"{k},{10.0 + 2.5 * k},0.3\n" for k in range(8)))
    ref = import_image_folder(_folder(tmp_path / "a", 8), tmp_path / "ra", {"hz": 1, "positions": pr},
                              progress=False)
    q = import_image_folder(_folder(tmp_path / "b", 8, darker=0.7), tmp_path / "rb", {"hz": 1, "positions": pq},
                            progress=False)
    doc = run_benchmark([ref], q, ["hog"], tolerance=0, progress=False, json_path=tmp_path / "o.json")
    assert doc["truth"] == "positions"
    # the reference frame nearest each query position (a tie goes to the first)
    assert json.loads((tmp_path / "o.json").read_text())["truth_frames"] == [2, 2, 3, 3, 4, 4, 5, 5]
    bare = import_image_folder(_folder(tmp_path / "c", 8), tmp_path / "rc", {"hz": 1}, progress=False)
    assert _cli(["bench", "sequence", str(ref), "--query", str(bare), "--methods", "hog"]) == 2
    assert "no truth" in capsys.readouterr().err
    r = precision_recall(np.array([0, 1, 2, 3]), np.array([0.9, 0.1, 0.8, 0.5]), np.array([True, False, True, True]))
    assert r == {"precision_at_100_recall": 0.75, "recall_at_100_precision": 0.75}


def test_real_sequence_folder(grief_root, tmp_path, capsys):
    """A real ordered pair of traverses (GRIEF season: summer, winter; frame k of both the same place) imported
    as image folders: whole-image HOG finds the winter frame's place within 2 frames far above chance."""
    season = grief_root / "season"
    if not (season / "season_00").is_dir():
        pytest.skip(f"no ordered traverse pair at {season}")
    ref = import_image_folder(season / "season_00", tmp_path / "summer", {"hz": 1}, progress=False)
    q = import_image_folder(season / "season_01", tmp_path / "winter", {"hz": 1, "aligned_with": ref},
                            progress=False)
    assert _cli(["bench", "sequence", str(ref), "--query", str(q), "--methods", "hog", "--tolerance", "2"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames"] == 101 and doc["truth"] == "frame alignment"
    assert doc["methods"]["hog"]["recall_at_1"] > 0.3           # chance is 5/101


def test_localise_refuses_a_run_without_odometry(tiny_world, tmp_path, capsys):
    """An image-folder run's odometry.csv holds the identity (no motion known): the replay refuses it, naming
    run.toml and the command that does localise such a run."""
    _, root = tiny_world
    run = import_image_folder(_folder(tmp_path / "seq", 3), tmp_path / "run", {"hz": 1}, progress=False)
    assert _cli(["localise", str(root), str(run), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "run.toml" in err and "odometry_source is 'none'" in err and "bench sequence" in err
