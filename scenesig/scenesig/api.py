"""The front door: build a map, localise a run, compare methods -- in three calls, results in memory.

::

    import scenesig

    summary = scenesig.build_map(["world/run00_sunny", "world/run01_night"], "world/run00_sunny", "maps/demo",
                                 layers=["signatures", "orb"])      # orb: for compare's second method
    loc = scenesig.localise("maps/demo", "world/run05_fog")           # nothing written
    loc.times, loc.poses            # (N,), (N, 4, 4): NaN before a first fix (without INS/GPS)
    loc.frames["lateral_error"]     # the per-frame table (frames.csv's columns)
    loc.metrics["lateral_error_m"]["median"]        # error keys only where the run has truth
    loc.write("out/fog")            # exactly the files ``scenesig localise`` writes
    rows = scenesig.compare("maps/demo", ["world/run05_fog"], methods=["signatures", "orb"])

The command line calls these (``scenesig build-map``, ``scenesig localise``, ``scenesig compare``), so a
result made here and one made there are the same bytes.  ``preset`` picks a settings preset
(:mod:`scenesig.presets`: ``default``, ``paper``); ``config`` overrides it, and a keyword that names a
setting (``layers``, ``oracle``) overrides ``config`` when given -- such keywords default to None, so an
unset one leaves ``config`` (then the preset, then the defaults) in force.  See ``docs/api.md``.
"""
from __future__ import annotations

from pathlib import Path

from scenesig.presets import apply_preset
from scenesig.surveys.localisation import Localisation

__all__ = ["build_map", "localise", "compare", "Localisation"]


def _read(run):
    from scenesig.surveys.run import SurveyRun, read_run

    # an absolute folder: worker processes (joblib's, reused across calls) may not share our working folder
    return run if isinstance(run, SurveyRun) else read_run(Path(run).resolve())


def build_map(runs, reference, out, *, layers=None, jobs: int = 1, scheduler=None, config: dict | None = None,
              preset: str | None = None, progress: bool = True, skip_corrupt: bool = False):
    """Build (or resume) a map; returns the build summary, a :class:`scenesig.mapping.build_summary.BuildSummary`
    (typed attributes; also a mapping of ``build_summary.json``'s content).

    Parameters
    ----------
    runs : training runs -- folders or :class:`scenesig.surveys.run.SurveyRun` objects already read.
    reference : the reference run (a folder, one of ``runs`` or not, or a run object): places are
        defined along it.
    out : the map folder.
    layers : the map layers to store (``scenesig build-map --layers``): a list or comma-separated text of
        :data:`scenesig.mapping.layers.LAYERS` names, ``"all"`` for every one; ``signatures`` is always
        built.  A method needs its layer (``compare(methods=["orb"])`` needs ``orb``).  None: ``config``'s
        ``layers``, else the default (``signatures``).
    jobs : places built in parallel (joblib processes); ``scheduler``: a Dask scheduler address or
        ``distributed.Client`` instead (needs the ``distributed`` extra).
    config : build overrides (:data:`scenesig.mapping.build.default_config`), on top of ``preset``.
    preset : a settings preset (:data:`scenesig.presets.PRESETS`), default the project's defaults.
    """
    from scenesig.localiser import firing
    from scenesig.mapping.build import build_map as _build_map
    from scenesig.surveys.run import SurveyRun, read_run

    if isinstance(runs, (str, Path, SurveyRun)):
        runs = [runs]
    loaded = [_read(r) for r in runs]
    if isinstance(reference, SurveyRun):
        ref = reference
    else:
        path = Path(reference).resolve()
        ref = next((r for r in loaded if r.root is not None and Path(r.root).resolve() == path), None)
        ref = ref or read_run(path)
    if layers is not None:
        from scenesig.mapping.layers import parse_layers

        config = {**(config or {}), "layers": parse_layers(layers)}     # the keyword over config's
    cfg = apply_preset("build", config, preset)
    summary = _build_map(loaded, ref, out, jobs=jobs, scheduler=scheduler, config=cfg, progress=progress,
                         skip_corrupt=skip_corrupt)
    # the places' firing rates, for the integrity monitor's sequential test (scenesig.localiser.firing)
    firing.for_map(out, loaded + ([ref] if all(r is not ref for r in loaded) else []))
    return summary


def localise(map, run, *, method: str = "signatures", oracle: str | None = None, every: int | None = None,
             config: dict | None = None, preset: str | None = None, realtime: bool = False, speed: float = 1.0,
             progress: bool = False, camera_check: bool = True) -> Localisation:
    """Localise one run against a map, in memory (write the CLI's files with :meth:`Localisation.write`).

    Parameters
    ----------
    map : the map folder, or a :class:`scenesig.mapping.store.MapStore` already open.
    run : the live run: a folder, or a :class:`scenesig.surveys.run.SurveyRun` already read.
    method : ``signatures`` or a point-feature baseline (``orb``, ``sift``, ``orb-all``, ``sift-all``).
    oracle : ``ins`` (start and reset from the run's INS/GPS: the paper's protocol) or ``none``; None:
        ``config``'s ``oracle``, else the preset's, else ``ins``.
    every : the detector on every N-th frame (default :data:`scenesig.localiser.replay.DEFAULT_EVERY`, 4).
    config : replay overrides (:data:`scenesig.localiser.replay.default_config`: ``localiser``, ``method``, ...), on
        top of ``preset``.
    realtime, speed : threads and one-slot mailboxes paced by the data clock instead (not repeatable).
    camera_check : check the run's calibration against its own images and odometry before replaying
        (the comparison with the map's camera is always made; a clearly incompatible run raises
        :class:`scenesig.surveys.errors.DataError`).
    """
    from scenesig.localiser.outputs import evaluate_localisation
    from scenesig.localiser.replay import DEFAULT_EVERY, ORACLES, default_config, localise_run
    from scenesig.surveys.settings import merge_settings

    cfg = apply_preset("localise", config, preset)
    mpd = merge_settings(default_config, cfg, "replay", open=("localiser", "method", "relocalise", "integrity"))
    oracle = mpd["oracle"] if oracle is None else oracle        # keyword > config > preset > default
    if oracle not in ORACLES:
        raise ValueError(f"oracle must be one of {', '.join(ORACLES)}, got {oracle!r}")
    loc, store = localise_run(map, run, method, every=DEFAULT_EVERY if every is None else int(every),
                              realtime=realtime, speed=speed, config=cfg, progress=progress, oracle=oracle,
                              camera_check=camera_check)
    evaluate_localisation(loc, store, mpd["max_path_distance_m"])
    return loc


def _metrics_of(map_root, run, method, oracle, every, config, preset) -> dict:
    return localise(map_root, run, method=method, oracle=oracle, every=every, config=config,
                    preset=preset).metrics


def compare(map, runs, *, methods, oracle: str | None = None, jobs: int = 1, scheduler=None, every: int | None = None,
            config: dict | None = None, preset: str | None = None) -> list[dict]:
    """Localise every run with every method; one row per run and method (in that order): a dict of the
    metrics (:attr:`Localisation.metrics`) whose first keys are ``run`` and ``method``.

    ``oracle`` and the other settings as in :func:`localise`.  ``jobs`` localisations run in parallel
    (joblib processes), or on a Dask cluster with ``scheduler`` (an address or a ``distributed.Client``;
    needs the ``distributed`` extra).  Nothing is written.
    """
    from scenesig.mapping.store import MapStore

    if isinstance(runs, (str, Path)) or not hasattr(runs, "__iter__"):
        runs = [runs]
    methods = [methods] if isinstance(methods, str) else list(methods)
    if not methods:
        raise ValueError("compare needs at least one method")
    runs = list(runs)
    map_arg = map
    if (jobs > 1 or scheduler is not None) and isinstance(map, MapStore):
        map_arg = map.root          # workers open the map themselves
    tasks = [(r, m) for r in runs for m in methods]
    if scheduler is not None:
        from scenesig.surveys.extras import require

        require("distributed", "distributed", "compare(scheduler=...)")
        from distributed import Client

        client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
        try:
            futs = [client.submit(_metrics_of, map_arg, r, m, oracle, every, config, preset, pure=False)
                    for r, m in tasks]
            results = client.gather(futs)
        finally:
            if not isinstance(scheduler, Client):
                client.close()
    elif jobs > 1:
        from joblib import Parallel, delayed

        results = Parallel(n_jobs=jobs, backend="loky")(
            delayed(_metrics_of)(map_arg, r, m, oracle, every, config, preset) for r, m in tasks)
    else:
        store = map if isinstance(map, MapStore) else MapStore.open(map)     # one open map, its cache shared
        results = [_metrics_of(store, r, m, oracle, every, config, preset) for r, m in tasks]
    rows = []
    for metrics in results:
        row = {"run": metrics["run"], "method": metrics["method"]}
        row.update({k: v for k, v in metrics.items() if k not in row})
        rows.append(row)
    return rows
