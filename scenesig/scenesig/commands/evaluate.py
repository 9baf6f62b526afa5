"""``scenesig evaluate LOCDIR [--truth FILE] [--map MAP]``: a localisation's errors against truth, on their own."""
from __future__ import annotations

import json


def register(groups):
    help = ("Evaluate a 'scenesig localise' output against truth (the run's truth.tum, or --truth FILE): "
            "fills in metrics.json's errors and frames.csv's error columns.")
    p = groups[""].add_parser("evaluate", help=help, description=help)
    p.add_argument("localisation", metavar="LOCDIR", help="'scenesig localise' output folder")
    p.add_argument("--truth", default=None, metavar="FILE",
                   help="TUM file of the run's exact truth (default: truth.tum, else groundtruth.tum, in the run "
                        "folder metrics.json names)")
    p.add_argument("--map", default=None, help="the map (default: the one metrics.json names; it must be the map "
                                               "the localisation was made against)")
    p.add_argument("--no-figure", action="store_true", help="do not redraw trajectory.png")
    p.set_defaults(_run=run)


def run(args) -> int:
    from scenesig.localiser.outputs import evaluate_folder

    metrics = evaluate_folder(args.localisation, truth=args.truth, map_root=args.map, figure=not args.no_figure)
    keys = ("method", "run", "truth_source", "lateral_error_m", "heading_error_deg", "lateral_error_map_m",
            "localised_fraction", "failures", "false_fixes", "bound_coverage_95", "lateral_bound_95_m_median")
    print(json.dumps({k: metrics[k] for k in keys if k in metrics}, indent=1))
    return 0
