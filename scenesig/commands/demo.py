"""``scenesig demo``: the main job -- simulate, build a map, localise, report."""
from __future__ import annotations

from ._types import positive_int


def register(groups):
    help = "The main job: simulate, build a map, localise, report."
    p = groups[""].add_parser("demo", help=help, description=help)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--jobs", type=positive_int, default=2, help="parallel workers (default 2)")
    p.add_argument("--preset", choices=["tiny", "demo", "begbroke"], default="demo",
                   help="simulated world (default demo, ≈300 m; tiny is a one-minute smoke run)")
    p.add_argument("--camera-hz", type=float, default=None,
                   help="camera rate of the simulated runs (default 10 Hz; the detector runs at 5 Hz either way)")
    p.set_defaults(_run=run)


def run(args) -> int:
    from scenesig.demo import run_demo

    config = {"preset": args.preset}
    if args.camera_hz:
        config["camera_hz"] = float(args.camera_hz)
    run_demo(args.out, jobs=int(args.jobs), config=config)
    return 0
