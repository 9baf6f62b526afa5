"""``scenesig map show|verify|add-points``: look at a map, check it, add point features to it."""
from __future__ import annotations

import json


def register(groups):
    help = ("List a map's generation and per-place experiences; with --out, figures of it: keyframes with "
            "signatures, a heat map.")
    p = groups["map"].add_parser("show", help=help, description=help)
    p.add_argument("map", help="map folder")
    p.add_argument("--place", type=int, default=None, help="only this place")
    p.add_argument("--out", default=None, help="figure folder")
    p.set_defaults(_run=run)
    help = "Verify a map's checksums and summarise it as JSON."
    v = groups["map"].add_parser("verify", help=help, description=help)
    v.add_argument("map", help="map folder (maps/NAME)")
    v.set_defaults(_run=run_verify)
    help = "Add the point-feature baseline's keyframe features to a map built without them."
    a = groups["map"].add_parser("add-points", help=help, description=help)
    a.add_argument("map", help="map folder")
    a.add_argument("--reference", required=True, metavar="RUN", help="the map's reference run")
    a.set_defaults(_run=run_add_points)
    help = ("Add point-feature layers (orb, sift, xfeat: the reference run's keyframe) to every place of a map "
            "built without them.")
    al = groups["map"].add_parser("add-layers", help=help, description=help)
    al.add_argument("map", help="map folder")
    al.add_argument("--reference", required=True, metavar="RUN", help="the map's reference run")
    al.add_argument("--layers", required=True, metavar="L,L,...", help="layers to add: orb, sift, xfeat")
    al.set_defaults(_run=run_add_layers)


def run(args) -> int:
    from scenesig.mapping.show import describe_map, show_map

    print(describe_map(args.map, args.place))
    if args.out:
        for p in show_map(args.map, args.out, args.place):
            print(p)
    return 0


def run_verify(args) -> int:
    from scenesig.mapping.store import verify_summary

    print(json.dumps(verify_summary(args.map), indent=1))
    return 0


def run_add_points(args) -> int:
    from scenesig.mapping.pointmap import add_to_map
    from scenesig.surveys.run import read_run

    print(json.dumps(add_to_map(args.map, read_run(args.reference)), indent=1))
    return 0


def run_add_layers(args) -> int:
    import sys

    from scenesig.mapping.layers import parse_layers, point_plan
    from scenesig.mapping.pointmap import add_to_map
    from scenesig.surveys.run import read_run

    try:
        plan = point_plan(parse_layers(args.layers))
    except ValueError as exc:
        print(f"scenesig map add-layers: error: {exc}", file=sys.stderr)
        return 2
    if plan["all"]:
        print(f"scenesig map add-layers: error: the -all layers ({', '.join(k + '-all' for k in plan['all'])}) need "
              f"every training run's keyframe and its visual solve: rebuild the map with build-map --layers",
              file=sys.stderr)
        return 2
    if not plan["reference"]:
        print("scenesig map add-layers: error: no point-feature layer given (orb, sift, xfeat)", file=sys.stderr)
        return 2
    print(json.dumps(add_to_map(args.map, read_run(args.reference), {"kinds": plan["reference"]}), indent=1))
    return 0
