"""``scenesig demo``: the main job -- simulate, build a map, localise, report."""
from __future__ import annotations

from ._types import positive_int

# conditions of the simulator a lifelong stage may learn (the base map must not have trained on it)
_UNSEEN = ("fog", "autumn", "morning", "night", "dusk", "rain", "snow")


def register(groups):
    help = "The main job: simulate, build a map, localise, report."
    p = groups[""].add_parser("demo", help=help, description=help)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--jobs", type=positive_int, default=2, help="parallel workers (default 2)")
    p.add_argument("--preset", choices=["tiny", "demo", "begbroke"], default="demo",
                   help="simulated world (default demo, ≈300 m; tiny is a one-minute smoke run)")
    p.add_argument("--camera-hz", type=float, default=None,
                   help="camera rate of the simulated runs (default 10 Hz; the detector runs at 5 Hz either way)")
    p.add_argument("--methods", default=None, metavar="M,M,...",
                   help="localisation methods (default signatures,orb,sift,orb-all,sift-all,xfeat-all,hybrid; "
                        "xfeat-all where the XFeat model is found); the map holds the layers these need")
    p.add_argument("--lifelong", action="store_true",
                   help="then the lifelong-map stage: an unseen condition's run A updates the map; run B of it "
                        "and another live run are localised before and after (scenesig/lifelong.py)")
    p.add_argument("--lifelong-map", choices=["day", "demo"], default="day",
                   help="base map of the lifelong stage: the demo's day training runs only (default) or the "
                        "demo's map")
    p.add_argument("--lifelong-condition", choices=list(_UNSEEN), default=None,
                   help="the condition the base map never trained on (default: night on the day map, autumn "
                        "on the demo's; the demo's map trained on all but fog, autumn and morning)")
    p.set_defaults(_run=run)


def run(args) -> int:
    from scenesig.demo import run_demo

    config = {"preset": args.preset}
    if args.camera_hz:
        config["camera_hz"] = float(args.camera_hz)
    if getattr(args, "methods", None):
        from scenesig.mapping.layers import method_layers

        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        try:
            for m in methods:
                method_layers(m)
        except ValueError as exc:
            import sys

            print(f"scenesig demo: error: --methods: {exc}", file=sys.stderr)
            return 2
        config["methods"] = methods
    run_demo(args.out, jobs=int(args.jobs), config=config)
    if getattr(args, "lifelong", False):
        from scenesig.demo import build_demo_report
        from scenesig.lifelong import run_lifelong

        run_lifelong(args.out, jobs=int(args.jobs), demo_config=config,
                     config={"condition": args.lifelong_condition, "base": args.lifelong_map})
        build_demo_report(args.out, config)
    return 0
