"""``scenesig localise MAP RUN --out DIR``: replay a traverse against a map."""
from __future__ import annotations

import json

from ._types import positive_int

#: the localisation methods: scene signatures, the point-feature baselines (``-all``: keyframes from
#: every training run; ``xfeat``: learned features, model from $SCENESIG_XFEAT_MODEL or
#: ~/.local/share/scenesig/models/xfeat.onnx) and both in one solve (``hybrid``: signatures + SIFT;
#: localiser.hybrid)
METHODS = ("signatures", "orb", "sift", "xfeat", "orb-all", "sift-all", "xfeat-all", "hybrid", "hybrid-orb",
           "hybrid-sift-all", "hybrid-orb-all")


def register(groups):
    from scenesig.presets import preset_names

    help = "Localise a replayed traverse against a map."
    p = groups[""].add_parser("localise", help=help, description=help)
    p.add_argument("map", help="map folder")
    p.add_argument("run", help="survey run to replay")
    p.add_argument("--method", choices=METHODS, default="signatures")
    p.add_argument("--match", choices=("ratio", "dapc", "gms", "mnn"), default=None,
                   help="point features (and hybrid's): mutual NN + ratio 0.8 (default for orb, sift), DAPC, GMS, or mutual NN "
                        "with cosine similarity > 0.82 (default for xfeat)")
    p.add_argument("--point-map", choices=("reference", "all"), default=None,
                   help="point features: the reference run's keyframe per place (orb, sift) or one per "
                        "training run (orb-all, sift-all)")
    p.add_argument("--no-prior-gating", action="store_true",
                   help="match / search the whole image instead of around the odometry prior's predictions")
    p.add_argument("--out", required=True, help="output folder")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--every", type=positive_int, default=None,
                      help="detector on every N-th frame (deterministic; default 4: 5 Hz on a 20 Hz camera)")
    mode.add_argument("--realtime", action="store_true", help="threads and queues, stale frames dropped")
    p.add_argument("--speed", type=float, default=1.0,
                   help="with --realtime: replay speed as a multiple of the recorded rate (default 1)")
    p.add_argument("--oracle", choices=("ins", "none"), default=None,
                   help="ins (the paper's protocol): start and reset from the run's INS/GPS; none: no "
                        "INS/GPS -- global localisation from the map at start-up, relocalisation when lost "
                        "(default: --config's oracle, else ins)")
    p.add_argument("--config", default=None,
                   help="replay options (overrides of localiser.replay.default_config: localiser, method, "
                        "relocalise, ...) as JSON text or a .json file")
    p.add_argument("--preset", choices=preset_names(), default=None,
                   help="settings preset under --config (paper: McManus et al. 2015's values where ours differ)")
    p.add_argument("--no-camera-check", action="store_true",
                   help="skip checking the run's calibration against its own images and odometry (the "
                        "comparison with the map's camera is always made)")
    p.set_defaults(_run=run, _parser=p)


def run(args) -> int:
    from scenesig.api import localise
    from scenesig.localiser.replay import method_options, resolve_config
    from scenesig.mapping.build import load_config
    from scenesig.presets import apply_preset

    try:
        opts = method_options(args.method, args.match, args.point_map, not args.no_prior_gating)
        config = load_config(args.config) or {}
        if opts:
            config["method"] = {**(config.get("method") or {}), **opts}
        resolve_config(apply_preset("localise", config, args.preset), args.method)   # misspelt options: exit 2
    except (TypeError, ValueError) as exc:
        args._parser.error(str(exc))
    loc = localise(args.map, args.run, method=args.method, every=args.every, realtime=bool(args.realtime),
                   speed=float(args.speed or 1.0), oracle=args.oracle, config=config or None, preset=args.preset,
                   progress=True, camera_check=not args.no_camera_check)
    metrics = loc.write(args.out)
    keys = ("method", "run", "oracle", "lateral_error_m", "heading_error_deg", "localised_fraction", "failures",
            "blind_fraction_over_20m", "first_fix_m", "relocalisations", "false_fixes", "lateral_bound_95_m_median",
            "bound_coverage_95", "truth_source", "realtime_factor", "frames_corrupt", "frames_dropped")
    print(json.dumps({k: metrics[k] for k in keys if k in metrics}, indent=1))
    return 0
