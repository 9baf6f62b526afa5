"""``scenesig localise MAP RUN --out DIR``: replay a traverse against a map."""
from __future__ import annotations

import json

from ._types import positive_int

#: the localisation methods: scene signatures, the point-feature baselines (``-all``: keyframes from
#: every training run) and both in one solve (``hybrid``: signatures + SIFT; localiser.hybrid)
METHODS = ("signatures", "orb", "sift", "orb-all", "sift-all", "hybrid", "hybrid-orb", "hybrid-sift-all",
           "hybrid-orb-all")


def register(groups):
    help = "Localise a replayed traverse against a map."
    p = groups[""].add_parser("localise", help=help, description=help)
    p.add_argument("map", help="map folder")
    p.add_argument("run", help="survey run to replay")
    p.add_argument("--method", choices=METHODS, default="signatures")
    p.add_argument("--match", choices=("ratio", "dapc", "gms"), default=None,
                   help="point features (and hybrid's): mutual NN + ratio 0.8 (default), DAPC, or GMS")
    p.add_argument("--point-map", choices=("reference", "all"), default=None,
                   help="point features: the reference run's keyframe per place (orb, sift) or one per "
                        "training run (orb-all, sift-all)")
    p.add_argument("--no-prior-gating", action="store_true",
                   help="match / search the whole image instead of around the odometry prior's predictions")
    p.add_argument("--out", required=True, help="output folder")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--every", type=positive_int, default=4, help="detector on every N-th frame (deterministic)")
    mode.add_argument("--realtime", action="store_true", help="threads and queues, stale frames dropped")
    p.add_argument("--speed", type=float, default=1.0,
                   help="with --realtime: replay speed as a multiple of the recorded rate (default 1)")
    p.add_argument("--oracle", choices=("ins", "none"), default="ins",
                   help="ins (default, the paper's protocol): start and reset from the run's INS/GPS; none: no "
                        "INS/GPS -- global localisation from the map at start-up, relocalisation when lost")
    p.set_defaults(_run=run, _parser=p)


def run(args) -> int:
    from scenesig.localiser.replay import localise, method_options

    try:
        opts = method_options(args.method, args.match, args.point_map, not args.no_prior_gating)
    except ValueError as exc:
        args._parser.error(str(exc))
    metrics = localise(args.map, args.run, args.out, method=args.method, every=args.every or 4,
                       realtime=bool(args.realtime), speed=float(args.speed or 1.0), oracle=args.oracle,
                       config={"method": opts} if opts else None)
    keys = ("method", "run", "oracle", "lateral_error_m", "heading_error_deg", "localised_fraction", "failures",
            "blind_fraction_over_20m", "first_fix_m", "relocalisations", "false_fixes", "lateral_bound_95_m_median",
            "bound_coverage_95", "truth_source", "realtime_factor", "frames_corrupt", "frames_dropped")
    print(json.dumps({k: metrics[k] for k in keys if k in metrics}, indent=1))
    return 0
