"""``scenesig build-map RUN... --reference RUN --out maps/NAME``: offline training of a map."""
from __future__ import annotations

import json
import sys

from ._types import positive_int


def register(groups):
    from scenesig.presets import preset_names

    help = "Build a map (a bank of scene signatures per place) from survey runs."
    p = groups[""].add_parser("build-map", help=help, description=help)
    p.add_argument("runs", nargs="+", metavar="RUN", help="training survey runs")
    p.add_argument("--reference", required=True, metavar="RUN", help="the map run that defines places")
    p.add_argument("--out", required=True, help="map folder, e.g. maps/NAME")
    p.add_argument("--jobs", type=positive_int, default=1, help="places built in parallel (joblib)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://host:8786")
    p.add_argument("--frames-per-run", type=positive_int, default=None, metavar="N",
                   help="frames each run gives a place: its nearest frame and neighbours 1 m apart within the "
                        "place's 10 m segment (default: enough for six images per place, at most 3 -- "
                        "1 with six runs or more)")
    p.add_argument("--config", default=None,
                   help="build options (overrides of mapping.build.default_config) as JSON text or a .json file")
    p.add_argument("--preset", choices=preset_names(), default=None,
                   help="settings preset under --config (default: the project's defaults; paper: McManus et al. "
                        "2015's values where ours differ -- scenesig config show --preset paper --differences)")
    p.add_argument("--layers", default=None, metavar="L,L,...",
                   help="map layers to store (mapping.layers): signatures (always built: it georeferences the "
                        "places) and the point-feature baselines orb, sift, xfeat (the reference run's keyframe) "
                        "and orb-all, sift-all, xfeat-all (every training run's keyframe); 'all' for every one. "
                        "Default: signatures, what the default method needs")
    p.add_argument("--features", choices=["hog", "xfeat", "hog+xfeat"], default=None,
                   help="what the signature banks are mined on: HOG cells (default, the paper's), XFeat's dense "
                        "descriptors, or both stacked (the XFeat ones need its model: $SCENESIG_XFEAT_MODEL); the "
                        "same as --config '{\"mining\": {\"features\": ...}}'")
    p.add_argument("--skip-corrupt", action="store_true",
                   help="leave out frames whose image is truncated or corrupt (counted in build_summary.json) "
                        "instead of stopping")
    p.set_defaults(_run=run, _parser=p)


def print_places(summary: dict, file=None) -> None:
    """Per place: runs, images mined (frames+augmented copies), signatures kept, rejected shapes by reason
    (to ``file``, default the current ``sys.stderr``)."""
    file = file or sys.stderr
    from scenesig.mapping.refine import REASONS

    reasons = ["no_data", "textureless", "not_converged", *REASONS]
    weak = set(summary.get("places_weak") or [])
    print(f"{'place':>5s} {'runs':>4s} {'images':>7s} {'kept':>5s}       rejected: "
          + " ".join(f"{r:>13s}" for r in reasons), file=file)
    for p in summary.get("per_place") or []:
        images = f"{p.get('frames') or 0}+{p.get('augmented') or 0}"
        rej = p.get("rejected") or {}
        print(f"{p['place']:5d} {p.get('runs') or 0:4d} {images:>7s} {p['signatures']:5d} "
              f"{'weak' if p['place'] in weak else '    '}{'':>12s}"
              + " ".join(f"{rej.get(r, 0):13d}" for r in reasons), file=file)


def run(args) -> int:
    from scenesig.api import build_map
    from scenesig.mapping.build import load_config, resolve_config
    from scenesig.presets import apply_preset

    config = load_config(args.config) or {}
    layers = None
    if args.layers is not None:
        from scenesig.mapping.layers import parse_layers

        try:
            layers = parse_layers(args.layers)
        except ValueError as exc:
            print(f"scenesig build-map: error: {exc}", file=sys.stderr)
            return 2
    if args.frames_per_run is not None:
        config["frames_per_run"] = int(args.frames_per_run)
    if args.features is not None:
        config["mining"] = {**dict(config.get("mining") or {}), "features": args.features}
    try:
        resolve_config(apply_preset("build", config, args.preset))     # a misspelt option: exit 2, nothing read
    except (TypeError, ValueError) as exc:
        args._parser.error(f"--config: {exc}")
    summary = build_map(args.runs, args.reference, args.out, layers=layers, jobs=args.jobs, scheduler=args.scheduler,
                        config=config, preset=args.preset, skip_corrupt=args.skip_corrupt)
    print_places(summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "per_place"}, indent=2))
    return 0
