"""``scenesig demo [--out DIR]``: the main job, end to end on the embedded simulated world.

1. **simulate** the ``demo`` world (≈300 m loop): six training runs of mixed appearance and five
   held-out live runs (night, fog, snow, dusk and a sunny day for the like-for-like comparison);
2. **build the map** from the training runs (scene-signature banks, landmarks and the keyframe points
   of the point-feature baselines it runs -- its layers, :func:`demo_layers` -- one file per place);
3. **localise** every live run with scene signatures and the four point-feature baselines: ORB and
   SIFT against the reference run's keyframes (``orb``, ``sift``: the paper's baseline) and against
   keyframes from every training run (``orb-all``, ``sift-all``, and the learned ``xfeat-all`` when its
   model file is found) -- and both in one solve (``hybrid``:
   signatures + SIFT, :mod:`scenesig.localiser.hybrid`; it takes the live SIFT features ``sift`` extracted)
   (deterministic replay: the detector
   at 5 Hz, as in the paper), starting from and reset by the run's INS/GPS (the paper's protocol), and
   with scene signatures once more without any INS/GPS (``--oracle none``: global localisation from the
   map, relocalisation when lost) -- the ``signatures-none`` entry;
4. the **matching experiment** (§4.2) on the live runs (computed in the localisation pool, beside the
   replays; its figures after them);
5. the **report** (``DIR/report/index.html``), a table on stdout and ``DIR/summary.json``::

       {"runs": [{"run": str, "conditions": [str],
                  "methods": {"signatures": METRICS, "orb": METRICS, "sift": METRICS,
                              "orb-all": METRICS, "sift-all": METRICS, "hybrid": METRICS,
                              "signatures-none": METRICS}}],
        "seconds": float, "localise_seconds_by_method": {METHOD: float}}

   where METRICS is the localiser's ``metrics.json``; ``localise_seconds_by_method`` sums each
   method's replay wall time over the live runs (a baseline that takes the live features its sibling
   already extracted -- ``sift-all`` after ``sift``, ``orb-all`` after ``orb`` -- is charged only what it
   adds).

Nothing is downloaded.  The cameras run at 10 Hz (and the detector on every 2nd frame: still 5 Hz)
so that the whole job fits in ten minutes on two cores; ``--camera-hz 20`` renders the paper's 20 Hz
(and runs the detector on every 4th frame).  Re-running with the same ``--out`` reuses what is
already there and valid: the simulated world if its settings match, the map (which resumes an
interrupted build), and localisations whose ``metrics.json`` exists.

Layout of ``DIR``: ``world/`` (survey runs), ``map/``, ``localise/RUN/METHOD/``, ``matching/``,
``report/``, ``summary.json``.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "run_demo", "build_demo_report", "localise_live_runs", "localise_groups"]

default_config = {
    "preset": "demo",
    "seed": 0,
    # Training runs of mixed appearance (the map must hold signatures that survive all of them) and
    # held-out live runs: the conditions the paper reports on (night, snow, fog, dusk) and a day run.
    "training": ["sunny", "overcast", "dusk", "night", "rain", "snow"],
    "live": ["night", "fog", "snow", "dusk", "sunny"],
    "reference": "sunny",            # condition of the map run (the first training run with it)
    "camera_hz": 10.0,
    "detector_hz": 5.0,              # the paper's detector rate; every = camera_hz / detector_hz
    # xfeat-all (learned features, Potje et al. 2024) runs when its model file is found
    # ($SCENESIG_XFEAT_MODEL or ~/.local/share/scenesig/models/xfeat.onnx); the map holds the layers these need
    "methods": ["signatures", "orb", "sift", "orb-all", "sift-all", "xfeat-all", "hybrid"],
    # methods also localised without INS/GPS (--oracle none); entry "<method>-none"
    "no_oracle_methods": ["signatures"],
}


def _log(msg: str) -> None:
    print(f"[demo] {msg}", flush=True)


def _simulate(world: Path, cfg: dict, jobs: int) -> dict:
    """Simulate the world unless ``world`` already holds exactly these runs."""
    from scenesig.surveys.sim.simulate import simulate

    conditions = list(cfg["training"]) + list(cfg["live"])
    summary_path = world / "simulate_summary.json"
    if summary_path.is_file():
        try:
            old = json.loads(summary_path.read_text())
            same = (old.get("preset") == cfg["preset"] and old.get("seed") == cfg["seed"]
                    and float(old.get("camera_hz", 0)) == float(cfg["camera_hz"])
                    and [r["conditions"][0] for r in old.get("runs", [])] == conditions)
        except (ValueError, KeyError, IndexError, TypeError):
            same = False
        if same:
            _log(f"world: reusing {world}")
            return old
    # a missing, different or half-written world is rendered again from scratch
    return simulate(world, preset=cfg["preset"], seed=cfg["seed"], runs=conditions,
                    camera_hz=float(cfg["camera_hz"]), jobs=jobs, overwrite=True)


def _localise_task(map_root, run_root: str, out: str, entry: str, every: int) -> tuple[str, str, dict]:
    """One localisation; ``entry`` is a method name, or ``<method>-none`` for the method without INS/GPS;
    ``map_root`` the map folder or an open :class:`scenesig.mapping.store.MapStore`."""
    from scenesig.localiser.replay import localise

    blind = entry.endswith("-none")
    method = entry.removesuffix("-none")
    metrics = localise(map_root, run_root, out, method=method, every=every, progress=False,
                       oracle="none" if blind else "ins")
    return Path(run_root).name, entry, metrics


def _one_thread() -> None:
    """A pool worker's OpenCV on one thread: the pool already keeps every core busy, and OpenCV's own
    threads (two per worker by default) would only contend with the other worker (results do not
    depend on it: OpenCV's parallel loops split rows, not sums); and the command line's process tuning
    (:func:`scenesig.runtime.configure`), which a fresh worker process does not inherit."""
    import cv2

    from scenesig.runtime import configure

    configure()
    cv2.setNumThreads(1)


def _localise_group(map_root: str, world: str, out: str, run: str, entries: list[str], every: int,
                    pooled: bool, env: dict | None = None) -> list[tuple[str, str, dict]]:
    """One run's localisations with the given entries, one after the other in one process (a
    module-level function so joblib can ship it to a worker).

    The entries of a group are the point-feature baselines of one kind (``sift`` and ``sift-all``):
    they replay the same frames with the same extraction settings, so the second one takes the live
    features the first extracted (:func:`scenesig.signatures.pointfeatures.feature_cache`; identical
    results, half the extraction -- SIFT on a VGA frame costs ~0.13 s of CPU), and the places the
    first one decoded (one map store, caching every place the run passes).
    """
    from scenesig.mapping.store import MapStore
    from scenesig.signatures.pointfeatures import feature_cache

    if pooled:
        _one_thread()
    # the parent's choices a reused worker process was not started with (the XFeat model file)
    os.environ.update(env or {})
    store = MapStore.open(map_root)
    if len(entries) > 1:             # every place the run passes stays decoded for the next replay
        store = MapStore.open(map_root, cache_size=len(store))
    with feature_cache():
        return [_localise_task(store, str(Path(world) / run), str(Path(out) / run / e), e, every)
                for e in entries]


def _matching_task(map_root: str, world: str, live: list[str], reference: str, pooled: bool):
    """The matching experiment (§4.2), run in the localisation pool beside the replays."""
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.run import read_run

    from .experiments import matching_experiment

    if pooled:
        _one_thread()
    store = MapStore.open(map_root)
    return matching_experiment(store, [read_run(Path(world) / n) for n in live],
                               reference=read_run(Path(world) / reference), progress=False)


#: CPU seconds of one live run's replay per entry, each on its own (demo world, the snow run), and of
#: the matching experiment: only their order matters, to start the longest jobs first so that the
#: workers finish together.
_COST = {"xfeat-all": 80.0, "xfeat": 70.0, "sift-all": 37.0, "sift": 30.0, "orb-all": 14.0, "orb": 9.0,
         "signatures": 8.6, "signatures-none": 7.8,
         "hybrid": 14.0, "hybrid-orb": 12.0}


def _feature_kind(entry: str) -> str:
    """The point-feature kind whose live features an entry extracts (``hybrid``: SIFT), or the entry."""
    from scenesig.localiser.hybrid import HYBRID_METHODS

    method = entry.removesuffix("-none")
    if method in HYBRID_METHODS:
        return HYBRID_METHODS[method][0]
    return method.split("-")[0]


_MATCHING_COST = 20.0


def localise_groups(todo: list[tuple[str, str]]) -> list[tuple[str, list[str]]]:
    """``(run, entry)`` pairs -> ``(run, [entry, ...])`` jobs: a run's point-feature entries of one kind
    (``orb`` / ``orb-all`` / ``hybrid-orb``, ``sift`` / ``sift-all`` / ``hybrid``, with or without INS/GPS)
    share a job, so the live features are extracted once; each other entry is its own; the costliest
    first (:data:`_COST`)."""
    from scenesig.mapping.pointmap import KINDS

    groups: dict = {}
    for run, entry in todo:
        kind = _feature_kind(entry)
        key = (run, kind) if kind in KINDS else (run, entry)
        groups.setdefault(key, []).append(entry)
    return sorted(((key[0], entries) for key, entries in groups.items()), key=lambda job: -_cost(job[1]))


def _cost(entries) -> float:
    return sum(_COST.get(e, 8.0) for e in entries)


def localise_live_runs(map_root, world, out, live: list[str], reference: str, entries: list[str], every: int,
                       jobs: int = 2, progress: bool = True):
    """The demo's localisation stage: every live run with every entry, and the matching experiment.

    ``world/RUN`` are the survey runs, ``out/RUN/ENTRY`` the localisations (one that already has its
    ``metrics.json`` is read, not redone).  The jobs (:func:`localise_groups`) and the matching
    experiment run in one pool of ``jobs`` workers, the costliest first, so the workers finish together.

    Returns
    -------
    metrics : dict ``(run, entry) -> metrics.json`` content.
    matching : the :class:`scenesig.experiments.MatchingResult` on the live runs.
    """
    from joblib import Parallel, delayed
    from tqdm import tqdm

    map_root, world, out = str(map_root), str(world), Path(out)
    todo = []
    metrics = {}
    for n in live:
        for m in entries:
            done = out / n / m / "metrics.json"
            if done.is_file():
                try:
                    metrics[(n, m)] = json.loads(done.read_text())
                    continue
                except ValueError:
                    pass
            todo.append((n, m))
    pooled = jobs > 1
    jobs_todo = localise_groups(todo)
    env = None
    if any(e.startswith("xfeat") for e in entries):
        from scenesig.signatures.xfeat import ENV_VAR, model_path

        env = {ENV_VAR: str(model_path())}
    calls = [delayed(_localise_group)(map_root, world, str(out), n, group, every, pooled, env)
             for n, group in jobs_todo]
    at = next((k for k, (_, group) in enumerate(jobs_todo) if _cost(group) < _MATCHING_COST), len(calls))
    calls.insert(at, delayed(_matching_task)(map_root, world, list(live), reference, pooled))
    bar = tqdm(total=len(todo), desc="localise", unit="run", disable=not progress)
    matching = None
    for res in Parallel(n_jobs=jobs, return_as="generator_unordered")(calls):
        if not isinstance(res, list):
            matching = res
            continue
        for n, m, met in res:
            metrics[(n, m)] = met
            bar.set_postfix_str(f"{n} {m}")
            bar.update(1)
    bar.close()
    return metrics, matching


def demo_layers(entries) -> list[str]:
    """The map layers the demo's entries need (:func:`scenesig.mapping.layers.method_layers`): it builds what it runs."""
    from scenesig.mapping.layers import method_layers, parse_layers

    return parse_layers([name for e in entries for name in method_layers(e)])


def _available_methods(methods) -> list[str]:
    """``methods`` without the XFeat ones when the model file is not found (nothing is downloaded)."""
    out = list(methods)
    if any(m.startswith("xfeat") for m in out):
        from scenesig.signatures.xfeat import ModelNotFoundError, model_path

        try:
            model_path()
        except ModelNotFoundError as exc:
            _log(f"leaving out {', '.join(m for m in out if m.startswith('xfeat'))}: {exc}")
            out = [m for m in out if not m.startswith("xfeat")]
    return out


def _fmt(v, digits=2):
    return "-" if v is None else f"{v:.{digits}f}"


def print_table(rows: list[dict], file=sys.stdout) -> None:
    """Per run and method: lateral median, heading median (against truth), lateral median against the
    map (simulated maps; '-' otherwise), localised fraction, failures, failures per km, blind share, and for
    a method without INS/GPS the distance to its first fix, its relocalisations and false fixes."""
    head = f"{'run':16s} {'conditions':10s} {'method':15s} {'lateral m':>9s} {'heading °':>9s} " \
           f"{'lat/map m':>9s} {'localised':>9s} {'failures':>8s} {'fail/km':>7s} {'blind>20m':>9s} " \
           f"{'1st fix m':>9s} {'relocs':>6s} {'false':>5s}"
    print(head, file=file)
    print("-" * len(head), file=file)
    for r in rows:
        for name, m in r["methods"].items():
            blind = m.get("oracle") == "none"
            print(f"{r['run']:16s} {','.join(r['conditions']):10s} {name:15s} "
                  f"{_fmt((m.get('lateral_error_m') or {}).get('median')):>9s} "
                  f"{_fmt((m.get('heading_error_deg') or {}).get('median')):>9s} "
                  f"{_fmt((m.get('lateral_error_map_m') or {}).get('median')):>9s} "
                  f"{_fmt(m['localised_fraction']):>9s} {m['failures']:>8d} {_fmt(m.get('failures_per_km'), 1):>7s} "
                  f"{_fmt(m['blind_fraction_over_20m'], 3):>9s} "
                  f"{_fmt(m.get('first_fix_m') if blind else None, 1):>9s} "
                  f"{str(m.get('relocalisations', '-')) if blind else '-':>6s} "
                  f"{str(m.get('false_fixes', '-')):>5s}", file=file)


def build_demo_report(out, config: dict | None = None, live_names: list[str] | None = None) -> Path:
    """The demo's report (``DIR/report``) from its localisations, matching experiment and, when the
    lifelong stage has run, its results (``DIR/lifelong/CONDITION/result``)."""
    from .report import build_report

    out = Path(out)
    cfg = merge_settings(default_config, config, "demo")
    if live_names is None:
        names = [r["name"] for r in json.loads((out / "world" / "simulate_summary.json").read_text())["runs"]]
        live_names = names[len(cfg["training"]):]
    extra = sorted(f.parent for f in (out / "lifelong").glob("*/result/lifelong.json"))
    return build_report([out / "localise", out / "matching", *extra], out / "report",
                        runs=[out / "world" / n for n in live_names])


def run_demo(out="out/demo", jobs: int = 2, config: dict | None = None) -> dict:
    """Run the whole demo into ``out``; returns ``summary.json``'s content."""
    from scenesig.mapping.build import build_map
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.io import atomic_write_bytes
    from scenesig.surveys.run import read_run

    from .plots import write_matching

    cfg = merge_settings(default_config, config, "demo")
    every = round(float(cfg["camera_hz"]) / float(cfg["detector_hz"]))
    if every < 1 or abs(every * float(cfg["detector_hz"]) - float(cfg["camera_hz"])) > 1e-6:
        raise ValueError(f"camera rate {cfg['camera_hz']} Hz must be a multiple of the detector rate "
                         f"{cfg['detector_hz']} Hz")
    if cfg["reference"] not in cfg["training"]:
        raise ValueError(f"reference condition {cfg['reference']!r} is not among the training runs")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    stages = {}

    _log(f"1/5 simulating the {cfg['preset']} world into {out / 'world'}")
    t = time.perf_counter()
    sim = _simulate(out / "world", cfg, jobs)
    stages["simulate"] = time.perf_counter() - t
    names = [r["name"] for r in sim["runs"]]
    n_train = len(cfg["training"])
    train_names, live_names = names[:n_train], names[n_train:]
    runs = {n: read_run(out / "world" / n) for n in names}
    ref_name = train_names[list(cfg["training"]).index(cfg["reference"])]

    methods = _available_methods(cfg["methods"])
    entries = methods + [f"{m}-none" for m in cfg["no_oracle_methods"]]
    layers = demo_layers(entries)
    _log(f"2/5 building the map from {len(train_names)} runs ({', '.join(train_names)}), reference {ref_name}, "
         f"layers {', '.join(layers)}")
    t = time.perf_counter()
    build = build_map([runs[n] for n in train_names], runs[ref_name], out / "map", jobs=jobs,
                      config={"layers": layers})
    from scenesig.localiser import firing  # the integrity monitor's sequential test needs the places' rates

    firing.for_map(out / "map", [runs[n] for n in train_names])
    stages["build_map"] = time.perf_counter() - t

    _log(f"3/5 localising {len(live_names)} live runs with {', '.join(entries)} (detector every {every} frames; "
         f"-none: without INS/GPS), and the matching experiment (§4.2) alongside")
    t = time.perf_counter()
    metrics, match_result = localise_live_runs(out / "map", out / "world", out / "localise", live_names, ref_name,
                                               entries, every, jobs)
    stages["localise"] = time.perf_counter() - t

    _log("4/5 matching experiment (§4.2): figures")
    t = time.perf_counter()
    write_matching(match_result, MapStore.open(out / "map"), out / "matching")
    stages["matching"] = time.perf_counter() - t

    _log("5/5 report")
    t = time.perf_counter()
    index = build_demo_report(out, cfg, live_names)
    stages["report"] = time.perf_counter() - t

    rows = [{"run": n, "conditions": list(runs[n].conditions),
             "methods": {m: metrics[(n, m)] for m in entries}} for n in live_names]
    # what each method costs inside the demo (its replays' wall time, summed over the live runs; the
    # second baseline of a kind does not extract the live features again)
    per_method = {m: float(sum(metrics[(n, m)].get("wall_seconds") or 0.0 for n in live_names))
                  for m in entries}
    summary = {"runs": rows, "seconds": time.perf_counter() - t0, "localise_seconds_by_method": per_method,
               "stage_seconds": stages, "map": {k: build.get(k) for k in (
                   "places", "signatures_per_place_mean", "bytes_per_place_mean", "landmark_depth_rel_error_median",
                   "layers", "bytes_per_place_by_layer_mean", "seconds_per_place_by_layer_mean",
                   "seconds_per_place_mean")},
               "config": cfg, "cpu_count": os.cpu_count(), "jobs": jobs,
               "report": str(index)}
    atomic_write_bytes(out / "summary.json", (json.dumps(summary, indent=2, allow_nan=False) + "\n").encode())
    print()
    print_table(rows)
    print()
    _log(f"done in {summary['seconds']:.0f} s ("
         + ", ".join(f"{k} {v:.0f} s" for k, v in stages.items()) + ")")
    _log(f"report: {index}")
    _log(f"summary: {out / 'summary.json'}")
    return summary
