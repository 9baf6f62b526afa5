"""Vet a built map before a long job: manifest, every place file's checksum and format, weak places.

:func:`check_map` reports every problem it finds (not only the first, as :meth:`MapStore.open`
does) as :class:`scenesig.surveys.check.Problem` lines:

* ``manifest.json`` missing (a ``journal.jsonl`` means an interrupted build: re-run build-map to
  resume it), not JSON, not a scenesig map, an unsupported version, malformed entries;
* each place file: present, its sha256 the manifest's, and it parses as a place of that index
  (:func:`scenesig.mapping.store.decode_place`: zip, arrays, format entry, dtypes);
* weak places -- too few signatures to localise reliably -- as warnings, where this scenesig has
  the weak-place rule (:func:`scenesig.mapping.coverage.weak_places`).
"""
from __future__ import annotations

import hashlib
from pathlib import Path

from scenesig.surveys.check import Problem
from scenesig.surveys.errors import DataError

from .store import JOURNAL, MANIFEST, PLACES_DIR, MapStore, decode_place

__all__ = ["check_map", "check_paths", "is_map", "camera_problems"]


def is_map(folder) -> bool:
    """True if ``folder`` looks like a map (a manifest, the journal of a build, or a places folder)."""
    folder = Path(folder)
    return (folder / MANIFEST).is_file() or (folder / JOURNAL).is_file() or (folder / PLACES_DIR).is_dir()


def _weak_place_problems(store: MapStore) -> list[Problem]:
    """Weak places as warnings (the rule lives in :mod:`scenesig.mapping.coverage`)."""
    from scenesig.mapping.coverage import MIN_SIGNATURES, weak_places

    return [Problem(str(store.root / store.places[i].file), None,
                    f"weak place {i}: {store.places[i].signatures} signatures (fewer than {MIN_SIGNATURES}): "
                    f"localisation there relies on odometry", "warning")
            for i in weak_places(store)]


def check_map(root) -> tuple[list[Problem], dict]:
    """Every problem of a map folder, and ``{"places": int, "places_checked": int, "bytes": int}``."""
    root = Path(root)
    stats = {"places": 0, "places_checked": 0, "bytes": 0}
    try:
        store = MapStore.open(root)
    except DataError as exc:
        return [Problem.from_error(exc)], stats
    problems: list[Problem] = []
    stats["places"] = len(store)
    for index, meta in store.places.items():
        path = root / meta.file
        try:
            raw = path.read_bytes()
        except OSError as exc:
            problems.append(Problem(str(path), None, f"place {index}'s file listed in {MANIFEST} is "
                                                     f"{'missing' if not path.exists() else 'unreadable'} ({exc.strerror})"))
            continue
        stats["bytes"] += len(raw)
        digest = hashlib.sha256(raw).hexdigest()
        if digest != meta.sha256:
            problems.append(Problem(str(path), None, f"checksum mismatch: {MANIFEST} says sha256 {meta.sha256[:16]}..., "
                                                     f"the file has {digest[:16]}... (corrupt, truncated or modified)"))
            continue
        try:
            decode_place(raw, path, index)
        except DataError as exc:
            problems.append(Problem.from_error(exc))
            continue
        stats["places_checked"] += 1
    problems += _weak_place_problems(store)
    return problems, stats


def camera_problems(runs, maps, images: bool = True) -> list[Problem]:
    """Each run's camera against each map's (:mod:`scenesig.mapping.camera_check`: size, intrinsics, extrinsic),
    and -- where images are checked -- each run's calibration against its own images and odometry.

    A run or map that does not open is left to its own check (which reports why).
    """
    from scenesig.surveys.run import read_run

    from .camera_check import assess, run_toml

    stores = []
    for m in maps:
        try:
            stores.append(MapStore.open(m))
        except DataError:
            pass
    out: list[Problem] = []
    for r in runs:
        try:
            run = read_run(r, check_images=False, skip=("groundtruth", "gps", "truth"))
        except DataError:
            continue
        where = str(run_toml(run))
        if images:
            for f in assess(run, None).findings:
                out.append(Problem(where, None, f"{f.what}: {f.reason}", f.severity))
        for store in stores:
            for f in assess(run, store, consistency=False).findings:
                out.append(Problem(where, None, f"camera differs from the map {store.root}'s -- {f.what}: {f.reason}",
                                   f.severity))
    return out


def check_paths(paths, max_gap_s: float | None = None, images: bool = True, jobs: int = 1,
                progress: bool = False) -> dict:
    """Check survey runs and maps; each path is a run, a map, or a folder holding runs and maps.

    Returns the ``scenesig check --json`` document (see :mod:`scenesig.commands.check`).
    """
    from scenesig.surveys.check import DEFAULT_MAX_GAP_S, check_run, is_run

    max_gap_s = DEFAULT_MAX_GAP_S if max_gap_s is None else float(max_gap_s)
    targets = []
    problems: list[Problem] = []
    for p in map(Path, paths):
        if is_run(p):
            targets.append(("run", p))
        elif is_map(p):
            targets.append(("map", p))
        elif p.is_dir() and (subs := [(("run" if is_run(q) else "map"), q) for q in sorted(p.iterdir())
                                      if q.is_dir() and (is_run(q) or is_map(q))]):
            targets += subs
        else:
            problems.append(Problem(str(p), None, "not a survey run (run.toml, frames.csv) or a map (manifest.json), "
                                                  "nor a folder holding any" if p.exists() else "not found"))
    checked = []
    # ``check RUN MAP``: the runs named on the command line against the maps named there (runs and maps
    # found inside a folder may be unrelated to each other)
    named = set(map(Path, paths))
    problems += camera_problems([p for k, p in targets if k == "run" and p in named],
                                [p for k, p in targets if k == "map" and p in named], images=images)
    for kind, p in targets:
        if kind == "run":
            found, stats = check_run(p, max_gap_s=max_gap_s, images=images, jobs=jobs, progress=progress)
        else:
            found, stats = check_map(p)
        problems += found
        checked.append({"path": str(p), "kind": kind, "problems": len(found), **stats})
    return {
        "paths": [str(p) for p in paths],
        "problems": [p.as_dict() for p in problems],
        "checked": checked,
        "summary": {"runs": sum(c["kind"] == "run" for c in checked), "maps": sum(c["kind"] == "map" for c in checked),
                    "images_checked": sum(c.get("images_checked", 0) for c in checked),
                    "places_checked": sum(c.get("places_checked", 0) for c in checked),
                    "errors": sum(p.severity == "error" for p in problems),
                    "warnings": sum(p.severity == "warning" for p in problems)},
    }
