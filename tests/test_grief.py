"""GRIEF adapter: both layouts on the real data and on small fabricated folders, and every error path."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from scenesig.surveys.errors import DataError
from scenesig.surveys.grief import GriefPair, detect_layout, load

# ---------------------------------------------------------------------------------- real data


def test_stromovka_real(grief_root):
    ds = load(grief_root / "stromovka")
    assert ds.kind == "sessions"
    assert len(ds.places) == 5 and ds.n_sessions == 12
    pairs = list(ds.pairs())
    assert len(pairs) == 660 == ds.n_pairs
    assert len(set(pairs)) == 660 and all(p.map != p.live for p in pairs)
    # location_1.txt row 1 = 0 69 106 -45 ...; row 2 starts with -69.
    assert ds.truth(GriefPair(0, 0, 1)) == 69.0
    assert ds.truth(GriefPair(0, 1, 0)) == -69.0
    assert ds.truth(GriefPair(0, 0, 3)) == -45.0
    img = ds.places[0].image(0)
    assert img.shape == (384, 1024, 3)
    assert ds.places[4].image(11, gray=True).shape == (384, 1024)
    assert ds.places[2].paths[6].name == "0703.jpg"  # session 07, place 03
    sets = ds.place_image_sets(reference=0, sessions=[s for s in range(12) if s != 5])
    assert len(sets) == 5 and len(sets[0]) == 11 and 5 not in sets[0].sessions
    assert sets[0].offsets[1] == 69.0 and sets[0].offsets[0] == 0.0


def test_season_real(grief_root):
    ds = load(grief_root / "season")
    assert ds.kind == "sequence"
    assert ds.session_names == ["season_00", "season_01"]
    pairs = list(ds.pairs())
    assert len(pairs) == 101
    assert all(p.map == 0 and p.live == 1 for p in pairs)
    # season_01/displacements.txt line 1 = "-109 -27".
    assert ds.truth(pairs[0]) == -109.0
    assert ds.places[0].displacement_xy(0, 1) == (-109.0, -27.0)
    assert ds.places[0].displacement(1, 0) == 109.0
    assert ds.places[100].paths[1].name == "000000100.jpg"


# ---------------------------------------------------------------------------------- fabricated


def _img(path: Path, seed: int = 0):
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 255, (24, 32, 3), dtype=np.uint8))


def _matrix(x0):
    x0 = np.asarray(x0, float)
    return x0[:, None] - x0[None, :]


def _write_matrix(path: Path, m):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join("\t".join(f"{v:g}" for v in row) + "\t\n" for row in m))


def make_sessions(root: Path, n_sessions=3, n_places=2):
    for s in range(1, n_sessions + 1):
        for p in range(1, n_places + 1):
            _img(root / "images" / f"{s:02d}{p:02d}.png", s * 10 + p)
    for p in range(1, n_places + 1):
        _write_matrix(root / "ground_truth" / f"location_{p}.txt",
                      _matrix(np.arange(n_sessions) * 7.0 * p))
    # The lossy summary exists in the real data; the reader must ignore it.
    (root / "ground_truth" / "angles.txt").write_text("garbage that is not a matrix\n")
    return root


def make_sequence(root: Path, n_frames=3, n_seasons=2):
    for s in range(n_seasons):
        for k in range(n_frames):
            _img(root / f"season_{s:02d}" / f"{k:09d}.png", 100 * s + k)
        if s:
            (root / f"season_{s:02d}" / "displacements.txt").write_text(
                "".join(f"{10 * s + k}\t{-s}\n" for k in range(n_frames)))
    return root


def test_sessions_layout_fabricated(tmp_path):
    # The folder name says "season" but the contents are the sessions layout.
    root = make_sessions(tmp_path / "season_like_name")
    assert detect_layout(root) == "sessions"
    ds = load(root)
    assert ds.kind == "sessions" and len(ds.places) == 2 and ds.n_sessions == 3
    assert ds.n_pairs == 2 * 3 * 2
    # M[i][j] = x0_i - x0_j with x0 = 0, 7, 14 (place 1) and 0, 14, 28 (place 2).
    assert ds.truth(GriefPair(0, 0, 2)) == -14.0
    assert ds.truth(GriefPair(1, 2, 0)) == 28.0
    assert ds.places[0].image(1, gray=True).shape == (24, 32)
    s = ds.places[1].image_set(reference=1)
    assert list(s.offsets) == [14.0, 0.0, -14.0] and np.isnan(s.offsets_y).all()


def test_sequence_layout_fabricated(tmp_path):
    root = make_sequence(tmp_path / "stromovka_like_name")
    assert detect_layout(root) == "sequence"
    ds = load(root)
    assert ds.kind == "sequence" and ds.n_pairs == 3
    assert [ds.truth(p) for p in ds.pairs()] == [10.0, 11.0, 12.0]
    assert ds.places[2].displacement_xy(0, 1) == (12.0, -1.0)


def test_sequence_three_seasons(tmp_path):
    ds = load(make_sequence(tmp_path / "d", n_frames=2, n_seasons=3))
    pairs = list(ds.pairs())
    assert len(pairs) == 4 and {p.live for p in pairs} == {1, 2}
    # season_01 frame 0 at +10, season_02 frame 0 at +20 -> 01 -> 02 is +10.
    assert ds.places[0].displacement(1, 2) == 10.0


def test_not_a_grief_folder(tmp_path):
    (tmp_path / "other").mkdir()
    with pytest.raises(DataError, match="not a GRIEF data set"):
        load(tmp_path / "other")
    with pytest.raises(DataError, match="not a directory"):
        load(tmp_path / "absent")


def test_ambiguous_layout(tmp_path):
    root = make_sessions(tmp_path / "d")
    (root / "season_00").mkdir()
    with pytest.raises(DataError, match="ambiguous"):
        load(root)


def test_missing_ground_truth(tmp_path):
    root = make_sessions(tmp_path / "d")
    (root / "ground_truth" / "location_2.txt").unlink()
    with pytest.raises(DataError, match="missing ground truth for place 02") as e:
        load(root)
    assert e.value.path.name == "location_2.txt"


def test_bad_number(tmp_path):
    root = make_sessions(tmp_path / "d")
    f = root / "ground_truth" / "location_1.txt"
    lines = f.read_text().splitlines()
    lines[1] = lines[1].replace("0", "x0", 1)
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="is not a number") as e:
        load(root)
    assert e.value.line == 2 and e.value.path == f


def test_wrong_row_length(tmp_path):
    root = make_sessions(tmp_path / "d")
    f = root / "ground_truth" / "location_2.txt"
    lines = f.read_text().splitlines()
    lines[2] = lines[2] + " 5"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="row has 4 values, expected 3") as e:
        load(root)
    assert e.value.line == 3


def test_wrong_row_count(tmp_path):
    root = make_sessions(tmp_path / "d")
    f = root / "ground_truth" / "location_1.txt"
    f.write_text("\n".join(f.read_text().splitlines()[:2]) + "\n")
    with pytest.raises(DataError, match="has 2 rows"):
        load(root)


def test_nonzero_diagonal(tmp_path):
    root = make_sessions(tmp_path / "d")
    m = _matrix([0, 7, 14])
    m[1, 1] = 3
    _write_matrix(root / "ground_truth" / "location_1.txt", m)
    with pytest.raises(DataError, match=r"M\[1\]\[1\]") as e:
        load(root)
    assert e.value.line == 2


def test_image_missing(tmp_path):
    root = make_sessions(tmp_path / "d")
    (root / "images" / "0201.png").unlink()
    with pytest.raises(DataError, match="image missing: session 02 of place 01"):
        load(root, strict=True)
    # GRIEF's own michigan set has gaps: by default the place just takes part in fewer pairs.
    ds = load(root)
    assert [p.name for p in ds.missing] == ["0201.png"]
    assert ds.n_pairs == 2 + 6
    assert all(1 not in (p.map, p.live) for p in ds.pairs() if p.place == 0)


def test_session_beyond_ground_truth(tmp_path):
    root = make_sessions(tmp_path / "d")
    _img(root / "images" / "0401.png")
    with pytest.raises(DataError, match="covers only 3 sessions"):
        load(root)


def test_ground_truth_without_images(tmp_path):
    root = make_sessions(tmp_path / "d")
    _write_matrix(root / "ground_truth" / "location_3.txt", _matrix([0, 1, 2]))
    with pytest.raises(DataError, match="no images"):
        load(root)


def test_duplicate_image(tmp_path):
    root = make_sessions(tmp_path / "d")
    _img(root / "images" / "0101.jpg")
    with pytest.raises(DataError, match="duplicate image"):
        load(root)


def test_sequence_missing_displacements(tmp_path):
    root = make_sequence(tmp_path / "d")
    (root / "season_01" / "displacements.txt").unlink()
    with pytest.raises(DataError, match="missing displacements file"):
        load(root)


def test_sequence_bad_displacement_line(tmp_path):
    root = make_sequence(tmp_path / "d")
    (root / "season_01" / "displacements.txt").write_text("1 2\n3 abc\n5 6\n")
    with pytest.raises(DataError, match="'abc' is not a number") as e:
        load(root)
    assert e.value.line == 2
    (root / "season_01" / "displacements.txt").write_text("1 2\n3\n5 6\n")
    with pytest.raises(DataError, match="expected 2 values") as e:
        load(root)
    assert e.value.line == 2


def test_sequence_count_mismatch(tmp_path):
    root = make_sequence(tmp_path / "d")
    (root / "season_01" / "000000002.png").unlink()
    with pytest.raises(DataError, match="has 2 images but season_00/ has 3"):
        load(root)
    root = make_sequence(tmp_path / "e")
    (root / "season_01" / "displacements.txt").write_text("1 2\n3 4\n")
    with pytest.raises(DataError, match="has 2 displacement lines but the folder has 3 images"):
        load(root)


def test_sequence_needs_season_00(tmp_path):
    root = make_sequence(tmp_path / "d")
    (root / "season_00").rename(root / "season_02")
    with pytest.raises(DataError, match="season_00"):
        load(root)


def test_undecodable_image(tmp_path):
    root = make_sequence(tmp_path / "d")
    (root / "season_01" / "000000001.png").write_bytes(b"not an image")
    ds = load(root)  # lazy: only loading the image fails
    with pytest.raises(DataError, match="does not decode") as e:
        ds.places[1].image(1)
    assert e.value.path.name == "000000001.png"
