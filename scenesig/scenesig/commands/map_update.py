"""``scenesig map update MAP LOCALISATION_DIR... [--out NEWMAP]``: a lifelong map update."""
from __future__ import annotations

import json


def register(groups):
    from scenesig.presets import preset_names

    help = "Add live runs' appearance to the places where their localisation was weak (lifelong map)."
    p = groups["map"].add_parser("update", help=help, description=help + " See mapping/update.py for the rule.")
    p.add_argument("map", help="map folder (updated in place, atomically, unless --out)")
    p.add_argument("localisations", nargs="+", metavar="LOCALISATION_DIR",
                   help="'scenesig localise' output folders (their runs must still exist)")
    p.add_argument("--out", default=None, metavar="NEWMAP", help="write the updated map here instead")
    p.add_argument("--runs-dir", action="append", default=[], metavar="DIR",
                   help="folder holding the map's training runs (default: beside the live runs; repeatable)")
    p.add_argument("--config", default=None, help="overrides of mapping.update.default_config (JSON)")
    p.add_argument("--preset", choices=preset_names(), default=None, help="settings preset under --config")
    p.add_argument("--allow-older-generation", action="store_true",
                   help="accept localisations made against an older generation of this map (never another map's)")
    p.set_defaults(_run=run)


def run(args) -> int:
    from pathlib import Path

    from scenesig.mapping.build import load_config
    from scenesig.mapping.update import read_localisation, update_map
    from scenesig.presets import apply_preset
    from scenesig.surveys.errors import DataError

    locs = [read_localisation(folder, args.runs_dir) for folder in args.localisations]
    try:
        summary = update_map(args.map, locs, out=args.out, runs_dirs=args.runs_dir, config=apply_preset("update", load_config(args.config), args.preset),
                             allow_older_generation=args.allow_older_generation)
    except OSError as exc:      # a read-only map folder, a full disk: say where, no traceback
        where = Path(exc.filename) if exc.filename else Path(args.out or args.map)
        raise DataError(where, f"cannot write: {exc.strerror or exc}") from None
    keys = ("map", "generation", "updated", "signatures_added", "bytes_added", "seconds_per_updated_place",
            "message")
    print(json.dumps({k: summary[k] for k in keys if k in summary}, indent=1))
    for name, verdict in summary["verdicts"].items():
        for i, r in verdict.items():
            if r["weak"]:
                what = f"added frame {r['frame']}" if r["frame"] is not None else f"skipped: {r['skip']}"
                print(f"{name}: place {i} weak ({r['reason']}): {what}")
    return 0
