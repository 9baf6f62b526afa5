"""``scenesig config show [--preset NAME]``: every stage's resolved settings as JSON."""
from __future__ import annotations

import json


def register(groups):
    from scenesig.presets import preset_names

    help = "Print every stage's resolved settings (build, localise per method, update, experiment) as JSON."
    p = groups["config"].add_parser("show", help=help, description=help)
    p.add_argument("--preset", choices=preset_names(), default="default",
                   help="settings preset (default: the project's defaults; paper: McManus et al. 2015's values "
                        "where ours differ, see docs/api.md)")
    p.add_argument("--differences", action="store_true",
                   help="print the preset's differences from the defaults (with the paper's sections) instead")
    p.set_defaults(_run=run)


def run(args) -> int:
    from scenesig.presets import PAPER_DIFFERENCES, resolve_settings

    if args.differences:
        print(json.dumps(PAPER_DIFFERENCES if args.preset == "paper" else [], indent=2))
        return 0
    print(json.dumps(resolve_settings(args.preset), indent=2, default=str))
    return 0
