"""Sequence place recognition on traverses without odometry: ``scenesig bench sequence MAP_RUNS... --query RUN``.

A robot that has only a camera -- no odometry, no GNSS -- can still say where it is along a route it
has driven before: which frame of the reference traverse its current frame shows.  This benchmark
answers that question for survey runs, any runs: typically image folders brought in with
``scenesig import images`` (:mod:`scenesig.surveys.importers.image_folder`), where frame i of two
traverses imported ``--aligned-with`` each other shows the same place (Nordland's and GRIEF
season's convention); nothing here knows a data set's name.

Map and truth
    ``MAP_RUNS``: the first is the reference (its frame p is place p); further map runs must be
    frame-aligned with it (other appearances of the same places: they train the signature banks and
    every method scores a place by its best map image).  The query's truth is frame-index
    correspondence when the query is aligned with the reference (``metadata.aligned_with``, either way
    round, or both aligned with the same run); otherwise, where both runs carry positions (``gps.csv``),
    the reference frame nearest the query frame's position.  A run with neither stops with an error.
    A query frame is correct when the matched reference frame is within ``--tolerance`` frames of the
    truth.

Methods: one harness for all, the place-recognition methods of ``bench places``
(:mod:`scenesig.benchmarks.places`, its docstring gives each in full) on the runs' frames --
``signatures`` (descriptor shortlist + bank verification, banks mined per reference frame from the
map runs' images of it), ``signatures-seq`` (the same verifications reasoned over the query and its
``sequence_length - 1`` predecessors: the odometry-free sequence constraint), ``hog``, ``seqslam`` and
``vlad`` -- plus ``xfeat`` where the XFeat model is present (:mod:`scenesig.benchmarks._models`):
XFeat keypoints of the query matched against every map image (mutual nearest neighbours on cosine,
upstream's ``min_cossim``), the place with the most matches first.  Settings are ``bench places``'
(chosen on stromovka's single-session protocol, never on the data reported).

Output (stdout): ``{"map_runs", "query", "frames", "places", "tolerance", "truth", "methods": {NAME:
{"recall_at_1", "precision_at_100_recall", "recall_at_100_precision", "cpu_ms_per_frame",
"ms_per_frame", "seconds_map"}}}``.  ``recall_at_1``: share of query frames whose best reference frame
is within the tolerance.  ``precision_at_100_recall``: precision when every query frame's best match is
accepted (the operating point of 100 % recall; every query frame has a true place, so it equals
``recall_at_1``, reported under the name the literature uses); ``recall_at_100_precision``: the share
of query frames accepted, most confident first (the method's own best score), before the first wrong
one.  ``cpu_ms_per_frame`` is process CPU time of the query side (all threads), ``ms_per_frame`` its
wall time; building the map side (mining, vocabulary, map descriptors) is ``seconds_map``.  ``--json
OUT`` also writes, per method, ``matches``: the matched reference frame of every query frame (the
localisation result of an odometry-free run), and ``truth_frames``: the true reference frame of each.

``--export-sim OUT --spacing M`` prepares a simulator pair instead: the runs given are simulated
survey runs (the first the reference); frames of the reference every M metres of its true path, and
for each other run the frame nearest each of them (true positions), are written as image folders
``OUT/<run>/`` with ``OUT/<run>_positions.csv`` (true positions, ``frame,x,y,z``), ready for
``scenesig import images --positions ... --aligned-with ...``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["METHODS", "RunSequences", "sequence_truth", "precision_recall", "run_benchmark", "export_sim",
           "main"]

METHODS = ("signatures", "signatures-seq", "hog", "seqslam", "vlad", "xfeat")

default_config = {
    "xfeat": {"top_k": 1024, "fit": "tile"},      # keypoints per image for the xfeat method
}


# ---------------------------------------------------------------------------------- data
class _Frame:
    """Frame ``index`` of every run that has it: the GRIEF place interface of :mod:`scenesig.benchmarks.places`."""

    def __init__(self, runs, index: int):
        self._runs, self.index = runs, index

    @property
    def sessions(self) -> list[int]:
        return [s for s, r in enumerate(self._runs) if self.index < len(r)]

    def image(self, session: int, gray: bool = False) -> np.ndarray:
        return self._runs[session].image(self.index, gray=gray)

    def displacement(self, i: int, j: int) -> float:
        # frame-aligned traverses carry no image-displacement truth: the banks are mined as if framed alike
        return 0.0


class RunSequences:
    """Survey runs as a GRIEF sequence-layout data set: session s is run s, place p is frame p."""

    kind = "sequence"

    def __init__(self, runs):
        self.runs = list(runs)
        self.root = Path(self.runs[0].root) if self.runs[0].root is not None else Path(self.runs[0].name)
        self.name = self.runs[0].name
        self.places = [_Frame(self.runs, i) for i in range(max(len(r) for r in self.runs))]

    @property
    def n_sessions(self) -> int:
        return len(self.runs)


def _aligned(a, b) -> bool:
    from scenesig.surveys.importers.image_folder import aligned_group

    return bool(aligned_group(a) & aligned_group(b))


def sequence_truth(reference, query) -> tuple[np.ndarray, str]:
    """The reference frame each query frame shows, and how it is known ("frame alignment" / "positions")."""
    from scenesig.surveys.errors import DataError

    if _aligned(reference, query):
        if len(reference) != len(query):
            raise DataError(query.root / "frames.csv", f"aligned with {reference.name} but has {len(query)} frames "
                                                       f"to its {len(reference)}")
        return np.arange(len(query)), "frame alignment"
    for r in (reference, query):
        if r.gps is None:
            raise DataError(r.root, f"run {r.name} is neither frame-aligned with the other run (import it with "
                                    "--aligned-with) nor has positions (gps.csv; --positions): no truth to score")
    def positions(r):
        g = r.gps
        return np.stack([np.interp(r.frame_times, g[:, 0], g[:, k]) for k in (1, 2)], axis=1)

    pr, pq = positions(reference), positions(query)
    d = np.linalg.norm(pq[:, None, :] - pr[None, :, :], axis=2)
    return d.argmin(axis=1), "positions"


def precision_recall(best: np.ndarray, confidence: np.ndarray, correct: np.ndarray) -> dict:
    """Precision at 100 % recall and recall at 100 % precision (module docstring)."""
    correct = np.asarray(correct, bool)
    order = np.argsort(-np.asarray(confidence, float), kind="stable")
    wrong = np.flatnonzero(~correct[order])
    first_wrong = int(wrong[0]) if len(wrong) else len(order)
    return {"precision_at_100_recall": float(correct.mean()) if len(correct) else 0.0,
            "recall_at_100_precision": first_wrong / len(order) if len(order) else 0.0}


# ---------------------------------------------------------------------------------- xfeat
def _xfeat(ds, pr, cfg: dict, timing: dict | None = None):
    from scenesig.benchmarks._models import xfeat_model
    from scenesig.benchmarks.places import _gray, _per_place
    from scenesig.signatures.xfeat import get_xfeat, match_mnn

    xcfg = {"model": xfeat_model(), **cfg["xfeat"]}
    xf = get_xfeat(xcfg)
    t_map = time.perf_counter()
    M = [xf.detect_and_compute(_gray(ds, m))[2] for m in pr.map_images]
    t_map = time.perf_counter() - t_map
    t0, c0 = time.perf_counter(), time.process_time()
    counts = np.zeros((len(pr.queries), len(M)))
    for qi, q in enumerate(pr.queries):
        d = xf.detect_and_compute(_gray(ds, q))[2]
        for mi, dm in enumerate(M):
            counts[qi, mi] = len(match_mnn(d, dm, xf.config["min_cossim"])[0])
    S = _per_place(counts, np.array([m[0] for m in pr.map_images]), pr.places)
    if timing is not None:
        timing["cpu"] = time.process_time() - c0
    return S, time.perf_counter() - t0, t_map


def _xfeat_available() -> bool:
    try:
        from scenesig.benchmarks._models import xfeat_model

        return Path(xfeat_model()).is_file()
    except Exception:      # ModelNotFoundError, or onnxruntime missing
        return False


# ---------------------------------------------------------------------------------- harness
def run_benchmark(map_runs, query, methods=None, tolerance: int = 2, jobs: int = 1, progress: bool = True,
                  config: dict | None = None, json_path=None, frames: tuple[int, int] | None = None) -> dict:
    """Score every method on one query run against the map runs; returns (and writes) the JSON document.

    Parameters
    ----------
    map_runs : survey-run folders (or :class:`~scenesig.surveys.run.SurveyRun`); the first is the reference.
    query : the query run.
    methods : names from :data:`METHODS`; None: all, ``xfeat`` only where its model is present.
    tolerance : frames either side of the truth that count as correct.
    frames : ``(start, stop)``: only frames start..stop-1 of every run (a segment of the route), else all.
    config : overrides of :data:`scenesig.benchmarks.places.default_config` (``shortlist``,
        ``sequence_length``, ``cache`` ...) and of this module's ``xfeat`` settings.
    """
    from scenesig.benchmarks import places
    from scenesig.surveys.errors import DataError
    from scenesig.surveys.run import SurveyRun, read_run

    runs = [r if isinstance(r, SurveyRun) else read_run(r) for r in list(map_runs) + [query]]
    if len(runs) < 2:
        raise ValueError("give at least one map run and a query run")
    if frames is not None:
        start, stop = int(frames[0]), int(frames[1])
        if not 0 <= start < stop:
            raise ValueError(f"frames must be START:STOP with 0 <= START < STOP, got {start}:{stop}")
        runs = [r.without_frames([i for i in range(len(r)) if not start <= i < stop]) for r in runs]
        if any(len(r) == 0 for r in runs):
            raise ValueError(f"frames {start}:{stop} leave a run without frames")
    ref, q = runs[0], runs[-1]
    for r in runs[1:-1]:
        if not _aligned(ref, r) or len(r) != len(ref):
            raise DataError(r.root, f"map run {r.name} is not frame-aligned with the reference {ref.name} (import "
                                    "it with --aligned-with the reference): a place is frame p of every map run")
    if int(tolerance) < 0:
        raise ValueError(f"tolerance must be >= 0 frames, got {tolerance}")
    if methods is None:
        methods = [m for m in METHODS if m != "xfeat" or _xfeat_available()]
    methods = [m.strip() for m in methods if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise ValueError(f"unknown method(s) {', '.join(bad) or '(none given)'}; choose from {', '.join(METHODS)}")
    config = dict(config or {})
    own = {"xfeat": {**default_config["xfeat"], **config.pop("xfeat", {})}}
    cfg = {**places.default_config, **config, **own}
    if int(cfg["sequence_length"]) < 1:
        raise ValueError(f"sequence length must be >= 1, got {cfg['sequence_length']!r}")
    truth, how = sequence_truth(ref, q)
    ds = RunSequences(runs)
    n_map = len(runs) - 1
    pr = places.Protocol(f"{ref.name}/{q.name}", [(p, s) for s in range(n_map) for p in range(len(ref))],
                         [(i, n_map) for i in range(len(q))], len(ref), int(tolerance), n_map)
    doc = {"map_runs": [r.name for r in runs[:-1]], "query": q.name, "frames": len(q), "places": len(ref),
           "tolerance": int(tolerance), "truth": how, "methods": {}}
    if frames is not None:
        doc["segment"] = [int(frames[0]), int(frames[0]) + len(ref)]
    full = {"truth_frames": truth.tolist(), "matches": {}}
    verified = None
    for name in methods:
        timing: dict = {}
        if name in ("signatures", "signatures-seq"):
            first = verified is None
            if first:
                vt: dict = {}
                verified = (*places._verify(ds, pr, cfg, jobs, progress, timing=vt), vt["cpu"])
            desc, V, secs, smap, cpu = verified
            smap = smap if first else 0.0
            S = places.single_scores(desc, V) if name == "signatures" else \
                places.sequence_scores(desc, V, int(cfg["sequence_length"]))
            # the sequence's extra cost is its few additions: the single-image verification is what both pay
            timing["cpu"] = cpu
        elif name == "xfeat":
            S, secs, smap = _xfeat(ds, pr, cfg, timing)
        else:
            S, secs, smap = places._RUNNERS[name](ds, pr, cfg, timing)
        best = np.argmax(S, axis=1)
        correct = np.abs(best - truth) <= int(tolerance)
        conf = S[np.arange(len(best)), best]
        n = len(truth)
        doc["methods"][name] = {"recall_at_1": float(correct.mean()),
                                **precision_recall(best, conf, correct),
                                "cpu_ms_per_frame": 1e3 * timing["cpu"] / n, "ms_per_frame": 1e3 * secs / n,
                                "seconds_map": float(smap)}
        if name in ("signatures", "signatures-seq"):
            doc["methods"][name]["shortlist"] = places.shortlist_size(cfg["shortlist"], pr.places)
        if name in ("signatures-seq", "seqslam"):
            doc["methods"][name]["sequence_length"] = int(cfg["sequence_length"])
        full["matches"][name] = best.tolist()
        print(f"{name}: recall@1 {correct.mean():.3f} (±{tolerance} frames), "
              f"{1e3 * timing['cpu'] / n:.1f} CPU ms/frame", file=sys.stderr)
    if json_path is not None:
        from scenesig.surveys.io import atomic_write_text

        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(json_path, json.dumps({**doc, **full}, indent=1))
    return doc


# ---------------------------------------------------------------------------------- simulator pair
def export_sim(run_paths, out, spacing: float = 4.0) -> dict:
    """Frame-aligned image folders from simulated runs of one world (module docstring); returns a summary."""
    from scenesig.surveys.run import read_run

    if not spacing > 0:
        raise ValueError(f"spacing must be > 0 m, got {spacing}")
    runs = [read_run(p) for p in run_paths]
    for r in runs:
        if r.truth_times is None and r.groundtruth_times is None:
            raise ValueError(f"run {r.name} has no truth.tum or groundtruth.tum: cannot align it by position")

    def xyz(r):
        which = "truth" if r.truth_times is not None else "groundtruth"
        return r.pose_at(r.frame_times, which)[:, :3, 3]

    ref = runs[0]
    pref = xyz(ref)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pref[:, :2], axis=0), axis=1))])
    marks = np.arange(0.0, arc[-1], float(spacing))
    picks = {ref.name: np.searchsorted(arc, marks)}
    gaps = {}
    for r in runs[1:]:
        p = xyz(r)
        d = np.linalg.norm(p[None, :, :2] - pref[picks[ref.name]][:, None, :2], axis=2)
        picks[r.name] = d.argmin(axis=1)
        gaps[r.name] = float(d.min(axis=1).max())
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for r in runs:
        folder = out / r.name
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir()
        p = xyz(r)
        rows = ["frame,x,y,z"]
        for k, i in enumerate(picks[r.name]):
            src = r.image_path(int(i))
            shutil.copyfile(src, folder / f"{k:06d}{src.suffix.lower()}")
            rows.append(f"{k},{float(p[i, 0])!r},{float(p[i, 1])!r},{float(p[i, 2])!r}")
        (out / f"{r.name}_positions.csv").write_text("\n".join(rows) + "\n")
    return {"folders": [str(out / r.name) for r in runs], "frames": int(len(marks)), "spacing_m": float(spacing),
            "reference": ref.name, "max_distance_to_reference_m": gaps,
            "camera_hz": float(ref.rates.get("camera_hz", 10.0))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scenesig bench sequence", description=__doc__.split("\n")[0])
    p.add_argument("map_runs", nargs="+", metavar="MAP_RUN",
                   help="reference run first, then further map runs frame-aligned with it")
    p.add_argument("--query", metavar="RUN", help="the query run (required unless --export-sim)")
    p.add_argument("--tolerance", type=int, default=2, help="frames either side of the truth counted correct "
                                                            "(default 2)")
    p.add_argument("--methods", default=None,
                   help=f"comma-separated, from {', '.join(METHODS)} (default: all; xfeat where its model is present)")
    p.add_argument("--json", default=None, metavar="OUT", help="also write the full document (with per-frame matches)")
    p.add_argument("--jobs", type=int, default=1, help="processes mining the signature banks")
    p.add_argument("--shortlist", default=None, help="signatures: places verified per query, N or a share (40%%)")
    p.add_argument("--sequence-length", type=int, default=None,
                   help="signatures-seq and seqslam: frames per sequence (default: bench places')")
    p.add_argument("--cache", default=None, help="folder caching the mined signature banks")
    p.add_argument("--frames", default=None, metavar="START:STOP",
                   help="only frames START..STOP-1 of every run (a segment of the route)")
    p.add_argument("--export-sim", default=None, metavar="OUT",
                   help="instead: write frame-aligned image folders of the simulated runs given (first = reference)")
    p.add_argument("--spacing", type=float, default=4.0, help="--export-sim: metres between reference frames")
    args = p.parse_args(argv)
    try:
        if args.export_sim is not None:
            print(json.dumps(export_sim(args.map_runs, args.export_sim, args.spacing), indent=1))
            return 0
        if args.query is None:
            p.error("--query RUN is required")
        config = {"cache": args.cache}
        if args.shortlist is not None:
            sl = args.shortlist.strip()
            config["shortlist"] = sl if sl.endswith("%") else int(sl)
        if args.sequence_length is not None:
            config["sequence_length"] = args.sequence_length
        frames = None
        if args.frames is not None:
            try:
                frames = tuple(int(v) for v in args.frames.split(":"))
                assert len(frames) == 2
            except (ValueError, AssertionError):
                p.error(f"--frames {args.frames!r}: expected START:STOP")
        doc = run_benchmark(args.map_runs, args.query, args.methods.split(",") if args.methods else None,
                            args.tolerance, jobs=max(1, args.jobs), config=config, json_path=args.json,
                            frames=frames)
    except ValueError as exc:     # DataError is a ValueError: the file and what is wrong
        print(f"scenesig bench sequence: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "sequence", *sys.argv[1:]]))
