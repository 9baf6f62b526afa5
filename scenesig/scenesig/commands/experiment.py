"""``scenesig experiment matching|localisation``: the paper's experiments (McManus et al. 2015, §4)."""
from __future__ import annotations

import json


def register(groups):
    help = "Feature-matching experiment (McManus et al. 2015, §4.2, Figs 11-14)."
    m = groups["experiment"].add_parser("matching", help=help, description=help)
    m.add_argument("map", help="map folder")
    m.add_argument("runs", nargs="+", metavar="RUN", help="test survey runs")
    m.add_argument("--reference", default=None, metavar="RUN",
                   help="the map's reference run (locates places by its truth)")
    m.add_argument("--methods", default="signatures,orb,sift")
    m.add_argument("--out", required=True)
    m.set_defaults(_run=run_matching)
    help = "Localisation figures (McManus et al. 2015, §4.3-4.4, Figs 15-25) from localise outputs."
    lo = groups["experiment"].add_parser("localisation", help=help, description=help)
    lo.add_argument("results", nargs="+", help="localise output folders or folders containing them")
    lo.add_argument("--runs", nargs="*", default=[], metavar="RUN",
                    help="survey runs (for raw INS errors and true speed)")
    lo.add_argument("--out", required=True)
    lo.set_defaults(_run=run_localisation)


def run_matching(args) -> int:
    from scenesig.experiments import matching_experiment
    from scenesig.mapping.store import MapStore
    from scenesig.plots import write_matching
    from scenesig.surveys.run import read_run

    store = MapStore.open(args.map)
    runs = [read_run(r) for r in args.runs]
    ref = read_run(args.reference) if args.reference else None
    res = matching_experiment(store, runs, ref, {"methods": args.methods.split(",")})
    write_matching(res, store, args.out)
    print(json.dumps(res.summary(), indent=1))
    return 0


def run_localisation(args) -> int:
    from scenesig.experiments import find_localise_outputs, find_runs, read_localise_output
    from scenesig.plots import localisation_figures

    outs = [read_localise_output(f) for f in find_localise_outputs(args.results)]
    runs = find_runs(args.runs, {o.run for o in outs}) if args.runs else {}
    figs = localisation_figures(outs, args.out, runs)
    print(json.dumps({"figures": [str(p) for p in figs["runs"].values()] + [str(figs["dead_reckoning"])]},
                     indent=1))
    return 0
