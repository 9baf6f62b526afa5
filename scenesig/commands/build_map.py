"""``scenesig build-map RUN... --reference RUN --out maps/NAME``: offline training of a map."""
from __future__ import annotations

import json
from pathlib import Path

from ._types import positive_int


def register(groups):
    help = "Build a map (a bank of scene signatures per place) from survey runs."
    p = groups[""].add_parser("build-map", help=help, description=help)
    p.add_argument("runs", nargs="+", metavar="RUN", help="training survey runs")
    p.add_argument("--reference", required=True, metavar="RUN", help="the map run that defines places")
    p.add_argument("--out", required=True, help="map folder, e.g. maps/NAME")
    p.add_argument("--jobs", type=positive_int, default=1, help="places built in parallel (joblib)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://host:8786")
    p.add_argument("--config", default=None,
                   help="build options (overrides of mapping.build.default_config) as JSON text or a .json file")
    p.set_defaults(_run=run)


def run(args) -> int:
    from mapping.build import build_map, load_config
    from surveys.run import read_run

    runs = [read_run(r) for r in args.runs]
    ref_path = Path(args.reference).resolve()
    reference = next((r for r in runs if r.root.resolve() == ref_path), None) or read_run(args.reference)
    summary = build_map(runs, reference, args.out, jobs=args.jobs, scheduler=args.scheduler,
                        config=load_config(args.config))
    print(json.dumps(summary, indent=2))
    return 0
