"""``scenesig compare MAP RUN... --methods signatures,orb``: localise every run with every method, print one
row of metrics per run and method (nothing written but ``--json``)."""
from __future__ import annotations

import json

from ._types import positive_int


def register(groups):
    from scenesig.presets import preset_names

    help = "Localise runs with several methods and print one row of metrics per run and method (JSON)."
    p = groups[""].add_parser("compare", help=help, description=help)
    p.add_argument("map", help="map folder")
    p.add_argument("runs", nargs="+", metavar="RUN", help="survey runs to localise")
    p.add_argument("--methods", default="signatures,orb,sift",
                   help="comma-separated methods (default signatures,orb,sift)")
    p.add_argument("--oracle", choices=("ins", "none"), default=None,
                   help="ins: start and reset from the runs' INS/GPS; none: no INS/GPS (default: --config's "
                        "oracle, else ins)")
    p.add_argument("--every", type=positive_int, default=None, help="detector on every N-th frame (default 4)")
    p.add_argument("--jobs", type=positive_int, default=1, help="localisations in parallel (joblib)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (needs the distributed extra)")
    p.add_argument("--config", default=None, help="replay options as JSON text or a .json file")
    p.add_argument("--preset", choices=preset_names(), default=None, help="settings preset under --config")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the rows to FILE")
    p.set_defaults(_run=run, _parser=p)


def run(args) -> int:
    from scenesig.api import compare
    from scenesig.localiser.replay import resolve_config
    from scenesig.mapping.build import load_config
    from scenesig.presets import apply_preset
    from scenesig.surveys.io import atomic_write_text

    from .localise import METHODS

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        args._parser.error(f"--methods: unknown {bad}; choose from {', '.join(METHODS)}")
    try:
        config = load_config(args.config)
        for m in methods:
            resolve_config(apply_preset("localise", config, args.preset), m)
    except (TypeError, ValueError) as exc:
        args._parser.error(str(exc))
    rows = compare(args.map, args.runs, methods=methods, oracle=args.oracle, jobs=args.jobs,
                   scheduler=args.scheduler, every=args.every, config=config, preset=args.preset)
    text = json.dumps(rows, indent=1, allow_nan=False) + "\n"
    if args.json:
        atomic_write_text(args.json, text)
    print(text, end="")
    return 0
