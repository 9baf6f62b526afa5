"""Reader for the GRIEF seasonal-change benchmark folders (Krajník et al., RAS 2017).

Two on-disk layouts exist and are recognised from a folder's *contents*, never its name, because
other data sets in the same layouts are run through the same code:

``sessions`` (e.g. ``grief/stromovka``, GRIEF's michigan set)
    ``images/SSLL.<ext>`` -- SS = session 01.., LL = place 01.. -- and
    ``ground_truth/location_N.txt`` for each place N: an n x n matrix, whitespace separated, one row
    per line, n = number of sessions.  ``M[i][j]`` is the truth for the pair (i, j): a scene point at
    column x in session i appears at column ``x + M[i][j]`` in session j.  ``ground_truth/angles.txt``
    is a lossy summary (its first row differs from the matrices by up to 15 px) and is never read.
    A place may lack an image in some session (GRIEF's own michigan set has such gaps); such a
    place simply takes part in fewer pairs, unless ``strict=True``.

``sequence`` (e.g. ``grief/season``)
    ``season_00/``, ``season_01/`` (more allowed), each with the same number of frames; frame k of
    every season shows the same place.  ``season_XX/displacements.txt`` line k = ``dx dy``: a scene
    point at (x, y) in season_00 frame k appears at (x + dx, y + dy) in season XX frame k.
    ``season_00/displacements.txt`` is optional (all zeros when present, since season_00 is the
    reference); a non-zero one is honoured, as the original GRIEF evaluation does, by taking
    differences: the displacement from season a to b is ``d_b - d_a``.

The protocol pairs (:meth:`GriefDataset.pairs`): every ordered (map i, live j) pair i != j of one
place for ``sessions``; (season_00 frame k, season_s frame k) for every k and s >= 1 for
``sequence`` (the published summer-map / winter-live direction).

Images load lazily; file-format problems raise :class:`scenesig.surveys.errors.DataError` naming the file
and, where there is one, the line.

Examples
--------
>>> ds = load("../shared/data/grief/stromovka")          # doctest: +SKIP
>>> ds.kind, len(ds.places), ds.n_pairs                    # doctest: +SKIP
('sessions', 5, 660)
>>> pair = next(ds.pairs()); ds.truth(pair)                # doctest: +SKIP
69.0
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import numpy as np

from scenesig.surveys.errors import DataError

__all__ = ["load", "detect_layout", "GriefDataset", "GriefPlace", "GriefPair", "PlaceImageSet",
           "IMAGE_SUFFIXES"]

log = logging.getLogger(__name__)

#: Image file suffixes the reader accepts (the GRIEF originals were PPM/BMP; ours are JPEG).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")

_SSLL = re.compile(r"^(\d{2})(\d{2})$")
_LOCATION = re.compile(r"^location_(\d+)\.txt$")
_SEASON = re.compile(r"^season_(\d+)$")


class GriefPair(NamedTuple):
    """One protocol pair: place index, map session index, live session index."""

    place: int
    map: int
    live: int


@dataclass(frozen=True)
class PlaceImageSet:
    """Images of one place under different appearance, aligned to a reference session.

    This is the training input of scene-signature mining: ``offsets[k]`` is the horizontal pixel
    displacement from the reference image to image k (a point at column x in the reference appears
    at ``x + offsets[k]`` in image k); ``offsets`` of the reference itself is 0.

    Attributes
    ----------
    place : str
        Place name (``"01"`` for sessions, the frame stem for sequence).
    reference : int
        Session index the offsets are relative to.
    sessions : tuple of int
        Session index of each image.
    paths : tuple of Path
        Image file of each session.
    offsets : ndarray, shape (n,)
        Horizontal displacement reference -> image k, pixels.
    offsets_y : ndarray, shape (n,)
        Vertical displacement where the data set has it (``sequence``), else NaN.
    """

    place: str
    reference: int
    sessions: tuple[int, ...]
    paths: tuple[Path, ...]
    offsets: np.ndarray
    offsets_y: np.ndarray

    def __len__(self) -> int:
        return len(self.paths)

    def image(self, k: int, gray: bool = False) -> np.ndarray:
        """Load image k (BGR uint8, or gray uint8)."""
        return _imread(self.paths[k], gray)

    def images(self, gray: bool = False) -> list[np.ndarray]:
        """Load all images of the set."""
        return [self.image(k, gray) for k in range(len(self))]


@dataclass
class GriefPlace:
    """One place: its image in each session and the pairwise displacement matrix.

    Attributes
    ----------
    name : str
        ``"01"``.. (sessions layout) or the frame file stem (sequence layout).
    index : int
        Position in :attr:`GriefDataset.places`.
    paths : list of (Path or None)
        Image file per session; None where the session has no image of this place.
    dx : ndarray, shape (n_sessions, n_sessions)
        ``dx[i, j]`` = horizontal displacement session i -> session j, pixels.
    dy : ndarray, shape (n_sessions, n_sessions)
        Vertical displacement where known (sequence layout), else NaN.
    truth_file : Path
        File the ground truth came from (for messages).
    """

    name: str
    index: int
    paths: list[Path | None]
    dx: np.ndarray
    dy: np.ndarray
    truth_file: Path

    @property
    def sessions(self) -> list[int]:
        """Session indices that have an image of this place."""
        return [s for s, p in enumerate(self.paths) if p is not None]

    def displacement(self, i: int, j: int) -> float:
        """Horizontal displacement (px) from session/image i to j: x_j = x_i + displacement."""
        return float(self.dx[i, j])

    def displacement_xy(self, i: int, j: int) -> tuple[float, float]:
        """(dx, dy) from session i to j; dy is NaN where the data set has no vertical truth."""
        return float(self.dx[i, j]), float(self.dy[i, j])

    def path(self, session: int) -> Path:
        """Image file of ``session``; DataError if this place has none there."""
        p = self.paths[session]
        if p is None:
            raise DataError(self.truth_file.parent.parent,
                            f"place {self.name} has no image in session {session + 1}")
        return p

    def image(self, session: int, gray: bool = False) -> np.ndarray:
        """Load this place's image in ``session`` (BGR uint8, or gray uint8)."""
        return _imread(self.path(session), gray)

    def image_set(self, reference: int = 0, sessions: Sequence[int] | None = None) -> PlaceImageSet:
        """This place's images as a :class:`PlaceImageSet` aligned to session ``reference``.

        Parameters
        ----------
        reference : int
            Session the offsets are measured from; must have an image.
        sessions : sequence of int, optional
            Sessions to include (default: all that have an image).  Leave-one-session-out training
            passes every session but the live one.
        """
        self.path(reference)  # raises if the reference session has no image
        chosen = self.sessions if sessions is None else [s for s in sessions
                                                          if self.paths[s] is not None]
        return PlaceImageSet(
            place=self.name, reference=reference, sessions=tuple(chosen),
            paths=tuple(self.paths[s] for s in chosen),
            offsets=np.array([self.dx[reference, s] for s in chosen], dtype=float),
            offsets_y=np.array([self.dy[reference, s] for s in chosen], dtype=float))


@dataclass
class GriefDataset:
    """A GRIEF-format data set.

    Attributes
    ----------
    kind : {"sessions", "sequence"}
        Which on-disk layout it was read from.
    root : Path
        The folder.
    places : list of GriefPlace
    session_names : list of str
        ``"01"``.. (sessions) or ``"season_00"``.. (sequence).
    missing : list of Path
        Expected images that are absent (sessions layout gaps); empty for complete grids.
    """

    kind: str
    root: Path
    places: list[GriefPlace]
    session_names: list[str]
    missing: list[Path] = field(default_factory=list)

    @property
    def name(self) -> str:
        """Folder name, for reports and figure file names (never used to detect the layout)."""
        return self.root.resolve().name

    @property
    def n_sessions(self) -> int:
        return len(self.session_names)

    def pairs(self) -> Iterator[GriefPair]:
        """The protocol's ordered (place, map, live) pairs.

        sessions: every ordered pair i != j of sessions both imaging the place (5 x 12 x 11 = 660
        on stromovka).  sequence: (season_00, season_s) for each frame and each s >= 1 (101 on
        season: summer map, winter live).
        """
        for place in self.places:
            have = place.sessions
            if self.kind == "sessions":
                for i in have:
                    for j in have:
                        if i != j:
                            yield GriefPair(place.index, i, j)
            else:
                if 0 not in have:
                    continue
                for j in have:
                    if j != 0:
                        yield GriefPair(place.index, 0, j)

    @property
    def n_pairs(self) -> int:
        return sum(1 for _ in self.pairs())

    def truth(self, pair: GriefPair) -> float:
        """Ground-truth horizontal displacement (px) of a pair, map -> live."""
        return self.places[pair.place].displacement(pair.map, pair.live)

    def place_image_sets(self, reference: int = 0,
                         sessions: Sequence[int] | None = None) -> list[PlaceImageSet]:
        """Every place as a :class:`PlaceImageSet` aligned to session ``reference``.

        Places without an image in ``reference`` are aligned to their first available session
        instead (the offsets stay exact, since every pairwise displacement is known).
        """
        out = []
        for place in self.places:
            ref = reference if place.paths[reference] is not None else place.sessions[0]
            out.append(place.image_set(ref, sessions))
        return out

    def describe(self) -> str:
        """One-line summary."""
        return (f"{self.name}: {self.kind} layout, {len(self.places)} places x "
                f"{self.n_sessions} sessions, {self.n_pairs} pairs"
                + (f", {len(self.missing)} images missing" if self.missing else ""))


# ----------------------------------------------------------------------------------------------
# reading


def detect_layout(root: str | Path) -> str:
    """Return ``"sessions"`` or ``"sequence"`` from what the folder holds.

    Raises
    ------
    DataError
        If the folder is missing, holds neither layout, or looks like both.
    """
    root = Path(root)
    if not root.is_dir():
        raise DataError(root, "not a directory (expected a GRIEF data set folder)")
    has_sessions = (root / "images").is_dir() or (root / "ground_truth").is_dir()
    seasons = [p for p in root.iterdir() if p.is_dir() and _SEASON.match(p.name)]
    has_sequence = bool(seasons)
    if has_sessions and has_sequence:
        raise DataError(root, "ambiguous GRIEF layout: holds both images/ or ground_truth/ "
                              "and season_NN/ folders")
    if has_sessions:
        return "sessions"
    if has_sequence:
        return "sequence"
    raise DataError(root, "not a GRIEF data set: expected images/SSLL.<ext> + "
                          "ground_truth/location_N.txt, or season_00/ + season_01/ with "
                          "displacements.txt")


def load(path: str | Path, strict: bool = False) -> GriefDataset:
    """Read a GRIEF data set folder, recognising its layout from its contents.

    Parameters
    ----------
    path : str or Path
        The data set folder.
    strict : bool
        sessions layout only: treat a place missing an image in some session as an error instead
        of leaving that session's pairs out (GRIEF's own michigan set has such gaps).

    Returns
    -------
    GriefDataset

    Raises
    ------
    DataError
        Missing files, non-numeric or wrongly shaped ground truth, image counts that do not match
        the ground truth -- the message names the file and, where there is one, the line.
    """
    root = Path(path)
    kind = detect_layout(root)
    if kind == "sessions":
        return _load_sessions(root, strict)
    return _load_sequence(root)


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _parse_number(tok: str, path: Path, line: int, what: str) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise DataError(path, f"{what}: {tok!r} is not a number", line) from None
    if not np.isfinite(v):
        raise DataError(path, f"{what}: {tok!r} is not finite", line)
    return v


def _read_matrix(path: Path, n: int | None) -> np.ndarray:
    """Read a whitespace-separated square matrix; ``n`` = expected size (None: any square)."""
    if not path.is_file():
        raise DataError(path, "missing ground-truth file")
    rows: list[list[float]] = []
    linenos: list[int] = []
    text = path.read_text(errors="replace").splitlines()
    for lineno, raw in enumerate(text, start=1):
        toks = raw.split()
        if not toks:
            continue
        linenos.append(lineno)
        rows.append([_parse_number(t, path, lineno, f"column {c + 1}")
                     for c, t in enumerate(toks)])
        width = n if n is not None else len(rows[0])
        if len(toks) != width:
            raise DataError(path, f"row has {len(toks)} values, expected {width} "
                                  f"(one per session)", lineno)
    size = n if n is not None else (len(rows[0]) if rows else 0)
    if len(rows) != size or size == 0:
        raise DataError(path, f"has {len(rows)} rows of {size} values; expected a square "
                              f"{size}x{size} matrix (one row and column per session)")
    m = np.asarray(rows, dtype=float)
    bad = np.flatnonzero(np.abs(np.diag(m)) > 0.5)
    if bad.size:
        i = int(bad[0])
        # A session compared with itself has no shift; anything else means a different format.
        raise DataError(path, f"diagonal entry M[{i}][{i}] = {m[i, i]:g}, must be 0", linenos[i])
    return m


def _load_sessions(root: Path, strict: bool) -> GriefDataset:
    img_dir, gt_dir = root / "images", root / "ground_truth"
    if not img_dir.is_dir():
        raise DataError(img_dir, "missing images folder (expected images/SSLL.<ext>)")
    if not gt_dir.is_dir():
        raise DataError(gt_dir, "missing ground_truth folder (expected location_N.txt per place)")

    grid: dict[tuple[int, int], Path] = {}
    for p in _image_files(img_dir):
        m = _SSLL.match(p.stem)
        if not m:
            log.warning("%s: ignored, name is not SSLL (session, place)", p)
            continue
        s, place = int(m.group(1)), int(m.group(2))
        if s < 1 or place < 1:
            raise DataError(p, "session and place numbers start at 01")
        if (s, place) in grid:
            raise DataError(p, f"duplicate image for session {s:02d} place {place:02d} "
                               f"(also {grid[(s, place)].name})")
        grid[(s, place)] = p
    if not grid:
        raise DataError(img_dir, "no SSLL images (SS = session 01.., LL = place 01..)")

    truth_files = {int(_LOCATION.match(p.name).group(1)): p
                   for p in gt_dir.iterdir() if _LOCATION.match(p.name)}
    place_ids = sorted({pl for _, pl in grid})
    for pl in sorted(set(truth_files) - set(place_ids)):
        raise DataError(truth_files[pl], f"ground truth for place {pl} but no images "
                                         f"images/SS{pl:02d}.*")

    n_img_sessions = max(s for s, _ in grid)
    suffixes = [p.suffix for p in grid.values()]
    suffix = max(set(suffixes), key=suffixes.count)  # for naming images that are absent
    places, missing, n_sessions = [], [], None
    for index, pl in enumerate(place_ids):
        gt = gt_dir / f"location_{pl}.txt"
        if pl not in truth_files:
            raise DataError(gt, f"missing ground truth for place {pl:02d}")
        m = _read_matrix(gt, n_sessions)
        if n_sessions is None:
            n_sessions = m.shape[0]
            if n_img_sessions > n_sessions:
                extra = sorted(p for (s, _), p in grid.items() if s > n_sessions)[0]
                raise DataError(extra, f"session {n_img_sessions:02d} has images but the ground "
                                       f"truth ({gt.name}) covers only {n_sessions} sessions")
        paths: list[Path | None] = []
        for s in range(1, n_sessions + 1):
            p = grid.get((s, pl))
            if p is None:
                expected = img_dir / f"{s:02d}{pl:02d}{suffix}"
                if strict:
                    raise DataError(expected, f"image missing: session {s:02d} of place {pl:02d} "
                                              f"(ground truth {gt.name} has {n_sessions} sessions)")
                missing.append(expected)
            paths.append(p)
        if sum(p is not None for p in paths) < 2:
            raise DataError(img_dir, f"place {pl:02d} has images in fewer than 2 sessions")
        places.append(GriefPlace(name=f"{pl:02d}", index=index, paths=paths, dx=m,
                                 dy=np.full_like(m, np.nan), truth_file=gt))
    if missing:
        log.warning("%s: %d images missing from the session x place grid; their pairs are left "
                    "out (first: %s)", root, len(missing), missing[0].name)
    return GriefDataset("sessions", root, places, [f"{s:02d}" for s in range(1, n_sessions + 1)],
                        missing)


def _read_displacements(path: Path, n_frames: int, required: bool) -> np.ndarray:
    """Read ``dx dy`` per line -> (n_frames, 2); zeros when optional and absent."""
    if not path.is_file():
        if required:
            raise DataError(path, "missing displacements file (one 'dx dy' line per frame)")
        return np.zeros((n_frames, 2))
    rows = []
    for lineno, raw in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        toks = raw.split()
        if not toks:
            continue
        if len(toks) != 2:
            raise DataError(path, f"expected 2 values 'dx dy', got {len(toks)}", lineno)
        rows.append([_parse_number(t, path, lineno, name) for t, name in zip(toks, ("dx", "dy"))])
    if len(rows) != n_frames:
        raise DataError(path, f"has {len(rows)} displacement lines but the folder has "
                              f"{n_frames} images (one line per frame)")
    return np.asarray(rows, dtype=float).reshape(n_frames, 2)


def _load_sequence(root: Path) -> GriefDataset:
    seasons = sorted((int(_SEASON.match(p.name).group(1)), p) for p in root.iterdir()
                     if p.is_dir() and _SEASON.match(p.name))
    numbers = [n for n, _ in seasons]
    if numbers[0] != 0:
        raise DataError(root / "season_00", "missing reference season folder season_00/")
    if len(seasons) < 2:
        raise DataError(root, "sequence layout needs season_00/ and at least season_01/")
    if numbers != list(range(len(numbers))):
        raise DataError(root, f"season folders must be numbered 00..{len(numbers) - 1} "
                              f"without gaps, found {', '.join(f'{n:02d}' for n in numbers)}")
    frames = [_image_files(folder) for _, folder in seasons]
    n = len(frames[0])
    if n == 0:
        raise DataError(seasons[0][1], "no images")
    for (_, folder), f in zip(seasons[1:], frames[1:]):
        if len(f) != n:
            raise DataError(folder, f"has {len(f)} images but {seasons[0][1].name}/ has {n}; "
                                    f"frame k of every season must show the same place")
    # d[s, k] = displacement of season s frame k relative to the common reference (season_00).
    d = np.stack([_read_displacements(folder / "displacements.txt", n, required=s > 0)
                  for s, folder in seasons])
    places = []
    for k in range(n):
        dx = d[None, :, k, 0] - d[:, None, k, 0]   # dx[a, b] = d_b - d_a
        dy = d[None, :, k, 1] - d[:, None, k, 1]
        places.append(GriefPlace(name=frames[0][k].stem, index=k,
                                 paths=[f[k] for f in frames], dx=dx, dy=dy,
                                 truth_file=seasons[1][1] / "displacements.txt"))
    return GriefDataset("sequence", root, places, [folder.name for _, folder in seasons])


def _imread(path: Path, gray: bool) -> np.ndarray:
    from scenesig.surveys.images import read_image  # local: keeps `import surveys.grief` light for metadata-only tools

    return read_image(path, gray)
