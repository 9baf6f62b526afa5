"""``scenesig simulate OUT --preset P --seed S``: render the simulated survey world as survey runs."""
from __future__ import annotations

import sys

from ._types import positive_int

#: the presets of :data:`scenesig.surveys.sim.world.PRESETS` (listed here so ``--help`` imports nothing heavy)
PRESETS = ("tiny", "demo", "compact", "begbroke")


def register(groups):
    p = groups[""].add_parser("simulate", help="Render the simulated survey world as survey runs.",
                              description="Render the simulated survey world as survey runs.")
    p.add_argument("out", help="output folder (one sub-folder per run)")
    p.add_argument("--preset", choices=PRESETS, default="demo")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--runs", default=None,
                   help="comma-separated conditions, one run each (default: the preset's list)")
    p.add_argument("--camera-hz", type=float, default=None, help="camera rate (default 20 Hz)")
    p.add_argument("--jobs", type=positive_int, default=1, help="runs rendered in parallel")
    p.add_argument("--overwrite", action="store_true", help="replace runs already in OUT (default: refuse)")
    p.add_argument("--start-m", dest="start_m", type=float, default=0.0,
                   help="distance along the route (m) where every run begins (default 0); the world is the same "
                        "for the same preset and seed, so such runs localise against a map built from another call")
    p.set_defaults(_run=run)


def run(args) -> int:
    from scenesig.surveys.sim.simulate import default_config, simulate

    runs = args.runs
    if isinstance(runs, str):
        runs = [r.strip() for r in runs.split(",") if r.strip()]
    camera_hz = args.camera_hz or default_config["camera_hz"]
    try:
        summary = simulate(args.out, preset=args.preset, seed=int(args.seed), runs=runs, camera_hz=float(camera_hz),
                           jobs=int(args.jobs or 1), overwrite=bool(args.overwrite), start_m=float(getattr(args, "start_m", 0.0) or 0.0))
    except (ValueError, FileExistsError) as exc:
        print(f"scenesig simulate: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(summary['runs'])} runs, {summary['frames']} frames in {summary['seconds']:.1f} s "
          f"({summary['frames_per_second']:.1f} frames/s) to {args.out}")
    for r in summary["runs"]:
        print(f"  {r['name']}: {', '.join(r['conditions'])}")
    return 0
