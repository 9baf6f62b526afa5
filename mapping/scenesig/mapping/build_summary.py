"""The build's stats journal and summary: ``build_stats.jsonl`` and ``build_summary.json`` of a map folder.

Each place's build stats (signatures kept, candidate shapes rejected by reason, images mined, landmark
depth errors against simulator truth, build time per layer) are journalled as the place is stored, so
they survive an interrupted build; once the places are built, :func:`_write_summary` aggregates them --
with the stored bytes per place, part and layer -- into ``build_summary.json``.  Places with fewer than
:data:`scenesig.mapping.coverage.MIN_SIGNATURES` signatures are reported as weak (McManus et al. 2015, §3.2).
:class:`BuildSummary` is that file, typed: what :func:`scenesig.build_map` returns and
:meth:`BuildSummary.read` reads back.
"""
from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from scenesig.mapping import layers as layers_mod
from scenesig.mapping.coverage import MIN_SIGNATURES
from scenesig.mapping.refine import REASONS
from scenesig.surveys.io import append_line, atomic_write_bytes

__all__ = ["BuildSummary"]


@dataclass(frozen=True, eq=False)
class BuildSummary(Mapping):
    """A map's build summary (``build_summary.json``), typed.

    The attributes are the file's keys; the object is also a read-only mapping of exactly the file's
    content (``summary["places"]``, ``dict(summary)``): code may read it as the typed object or as the JSON.
    A key this class does not know (a newer writer) is kept in the mapping; a key an older map lacks is
    ``None``.

    Attributes
    ----------
    places : number of places built.
    signatures_per_place_mean : mean signatures kept per place.
    features : the cell descriptor the banks were mined on (``hog``, ``xfeat``, ``hog+xfeat``).
    layers : the map layers built (:mod:`scenesig.mapping.layers`).
    places_weak : places with fewer than ``min_signatures`` signatures.
    per_place : per place: runs, images, frames, augmented copies, signatures, rejected shapes by reason.
    seconds : build wall time.
    (and the byte, time, landmark-depth and rejection statistics named like the file's keys)
    """

    places: int
    signatures_per_place_mean: float
    features: str | None = None
    bytes_per_place_mean: float | None = None
    bytes_per_place_by_part_mean: dict[str, float] | None = None
    layers: list[str] | None = None
    bytes_per_place_by_layer_mean: dict[str, float] | None = None
    seconds_per_place_by_layer_mean: dict[str, float] | None = None
    seconds_per_place_mean: float | None = None
    landmark_depth_rel_error_median: float | None = None
    landmark_depth_rel_error_quartiles: list[float] | None = None
    landmarks_with_truth: int | None = None
    landmark_depth_rel_error_median_single_depth: float | None = None
    landmarks_single_depth: int | None = None
    rejected: dict[str, int] | None = None
    frames_corrupt: int | None = None
    corrupt_frames: list[str] | None = None
    places_weak: list[int] | None = None
    min_signatures: int | None = None
    per_place: list[dict] | None = None
    seconds: float | None = None
    _doc: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_dict(cls, doc: dict) -> "BuildSummary":
        known = {f.name for f in fields(cls) if f.name != "_doc"}
        return cls(**{k: v for k, v in doc.items() if k in known}, _doc=dict(doc))

    @classmethod
    def read(cls, map_root) -> "BuildSummary":
        """The summary of the map at ``map_root`` (its ``build_summary.json``)."""
        from scenesig.surveys.errors import DataError

        path = Path(map_root) / "build_summary.json"
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise DataError(path, "no build summary: the map was not built by build-map (or the build did not "
                                  "finish)") from None
        except json.JSONDecodeError as e:
            raise DataError(path, f"not valid JSON: {e}") from None
        if not isinstance(doc, dict) or "places" not in doc:
            raise DataError(path, "not a build summary (no 'places')")
        return cls.from_dict(doc)

    def to_dict(self) -> dict:
        """The file's content (a copy)."""
        return json.loads(json.dumps(self._doc))

    def __getitem__(self, key: str) -> Any:
        return self._doc[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._doc)

    def __len__(self) -> int:
        return len(self._doc)

    def __eq__(self, other) -> bool:
        return isinstance(other, Mapping) and dict(self._doc) == dict(other)

    def __repr__(self) -> str:
        return (f"BuildSummary(places={self.places}, signatures_per_place_mean={self.signatures_per_place_mean}, "
                f"layers={self.layers}, places_weak={self.places_weak})")


def _weak_message(summary: dict, allstats: dict) -> str:
    weak = summary["places_weak"]
    runs = sorted({st.get("runs", 0) for i, st in allstats.items() if i in weak})
    return (f"{len(weak)} of {summary['places']} places have fewer than {MIN_SIGNATURES} signatures and will "
            f"rarely localise: {_index_ranges(weak)} (seen by {'/'.join(map(str, runs))} runs; per-place "
            f"counts and rejection reasons in build_summary.json 'per_place'). More training runs of "
            f"different appearance, or more frames per run (--frames-per-run), give them more.")


def _index_ranges(idx) -> str:
    """``[0, 1, 2, 5, 7, 8]`` -> ``"0-2, 5, 7-8"``."""
    idx = sorted(int(i) for i in idx)
    parts, start = [], None
    for k, i in enumerate(idx):
        if start is None:
            start = i
        if k + 1 == len(idx) or idx[k + 1] != i + 1:
            parts.append(f"{start}" if start == i else f"{start}-{i}")
            start = None
    return ", ".join(parts)


def _append_stats(out: Path, st: dict) -> None:
    """Journal one place's build stats just before its file is written, so they survive an interruption
    (a resumed build skips the place and would otherwise lose them); a later line for a place wins."""
    append_line(Path(out) / "build_stats.jsonl", json.dumps(st))


def _read_stats(out: Path) -> dict:
    """Every place's stats in ``build_stats.jsonl`` (this and earlier runs; a later line wins)."""
    per_place_path = out / "build_stats.jsonl"
    allstats = {}
    for line in (per_place_path.read_text().splitlines() if per_place_path.exists() else []):
        try:
            st = json.loads(line)
        except json.JSONDecodeError:  # a torn last line of a killed build: that place was rebuilt
            continue
        allstats[st["place"]] = st
    return allstats


def _write_summary(out: Path, places, allstats: dict, seconds: float, corrupt_files=()) -> dict:
    """``build_summary.json`` from every place's stats (:func:`_read_stats`)."""
    path = out / "build_summary.json"
    allstats = {p.index: allstats[p.index] for p in places if p.index in allstats}
    files = sorted((out / "places").glob("place_*.npz"))
    sizes = [f.stat().st_size for f in files]
    errs = [e for st in allstats.values() for e in st["depth_rel_errors"]]
    # truth spread of each error's patch ((q75 - q25) / median of its depths): < 0.3 = one surface
    spread = [s for st in allstats.values() for s in st.get("depth_truth_spread", [np.nan] * len(st["depth_rel_errors"]))]
    single = [e for e, s in zip(errs, spread) if s < 0.3]
    rejected = {"not_converged": 0, **{r: 0 for r in REASONS}}
    for st in allstats.values():
        for k, v in st["rejected"].items():
            rejected[k] = rejected.get(k, 0) + v
    summary = {
        "places": len(places),
        "signatures_per_place_mean": float(np.mean([st["signatures"] for st in allstats.values()])) if allstats else 0.0,
        # the cell descriptor the banks were mined on (mining's ``features``: hog, xfeat, hog+xfeat)
        # (a map whose places differ -- not made by build-map -- lists each, comma-separated)
        "features": ",".join(sorted({st.get("features", "hog") for st in allstats.values()})) or "hog",
        "bytes_per_place_mean": float(np.mean(sizes)) if sizes else 0.0,
        # where the bytes go: the scene-signature bank and its landmarks, the point-feature baseline's
        # keyframe features, the keyframe image for figures, and the metadata
        "bytes_per_place_by_part_mean": _bytes_by_part(files),
        # the same per map layer (mapping.layers): what each layer costs a place, stored and built
        "layers": _summary_layers(allstats, files),
        "bytes_per_place_by_layer_mean": _bytes_by_part(files, by_layer=True),
        "seconds_per_place_by_layer_mean": _seconds_by_layer(allstats),
        "seconds_per_place_mean": float(np.mean([st["seconds"] for st in allstats.values()])) if allstats else 0.0,
        "landmark_depth_rel_error_median": float(np.median(errs)) if errs else None,
        "landmark_depth_rel_error_quartiles": [float(q) for q in np.percentile(errs, [25, 50, 75])] if errs else None,
        "landmarks_with_truth": len(errs),
        # patches on one surface only (no depth discontinuity inside): the truth is unambiguous there
        "landmark_depth_rel_error_median_single_depth": float(np.median(single)) if single else None,
        "landmarks_single_depth": len(single),
        "rejected": rejected,
        # training frames left out because their image failed strict decoding (--skip-corrupt)
        "frames_corrupt": len(corrupt_files),
        "corrupt_frames": list(corrupt_files),
        # places with fewer than MIN_SIGNATURES signatures: too few to localise under changed appearance
        "places_weak": sorted(i for i, st in allstats.items() if st["signatures"] < MIN_SIGNATURES),
        "min_signatures": MIN_SIGNATURES,
        # per place: runs that see it, images mined (frames and augmented copies), signatures kept, and
        # the candidate shapes rejected by reason
        "per_place": [{k: st.get(k) for k in ("place", "runs", "images", "frames", "augmented", "signatures",
                                              "rejected")} for _, st in sorted(allstats.items())],
        "seconds": seconds,
    }
    atomic_write_bytes(path, (json.dumps(summary, indent=2) + "\n").encode())
    return summary


#: Parts of a place file, by member-name prefix (mapping.store's layout).
_PARTS = {"signatures": ("bank/", "landmarks", "covariances", "classifier_ids"), "point_features": ("points/",),
          "keyframe": ("keyframe",)}


def _summary_layers(allstats: dict, files) -> list:
    """The layers the places were built with (from the journal; else from a place file's members)."""
    seen = [name for st in allstats.values() for name in st.get("seconds_by_layer", {})]
    if not seen and files:
        import zipfile

        with zipfile.ZipFile(files[0]) as z:
            seen = [layers_mod.layer_of_member(i.filename) for i in z.infolist()]
    return [name for name in layers_mod.LAYERS if name in set(seen)]


def _seconds_by_layer(allstats: dict) -> dict:
    """Mean build seconds per place of each layer (places whose stats record it)."""
    acc: dict = {}
    for st in allstats.values():
        for k, v in (st.get("seconds_by_layer") or {}).items():
            acc.setdefault(k, []).append(float(v))
    return {k: float(np.mean(acc[k])) for k in layers_mod.LAYERS if k in acc}


def _bytes_by_part(files, by_layer: bool = False) -> dict:
    """Mean stored (compressed) bytes per place file of each part in :data:`_PARTS` (the rest: ``meta``),
    or with ``by_layer`` of each map layer (:func:`scenesig.mapping.layers.layer_of_member`)."""
    import zipfile

    totals = {} if by_layer else {k: 0 for k in (*_PARTS, "meta")}
    for f in files:
        with zipfile.ZipFile(f) as z:
            for info in z.infolist():
                if by_layer:
                    part = layers_mod.layer_of_member(info.filename)
                    totals.setdefault(part, 0)
                else:
                    part = next((k for k, prefixes in _PARTS.items() if info.filename.startswith(prefixes)), "meta")
                # the member's share of the file: its compressed data plus its local and central headers
                totals[part] += info.compress_size + 30 + 46 + 2 * len(info.filename.encode())
    return {k: (v / len(files) if files else 0.0) for k, v in totals.items()}
