"""``scenesig check PATH...``: vet survey runs and maps before a long job.

Each PATH is a survey run, a map, or a folder holding runs and maps (e.g. a simulated world).  One
line per problem, ``FILE[:LINE]: error|warning: reason``, then a summary; exit 0 when there is no
error, 2 otherwise; ``--json OUT`` writes the same for machines::

    {"paths": [str], "problems": [{"file", "line", "reason", "severity"}],
     "checked": [{"path", "kind": "run"|"map", "problems", ...counts}],
     "summary": {"runs", "maps", "images_checked", "places_checked", "errors", "warnings"}}
"""
from __future__ import annotations

import sys


def register(groups):
    p = groups[""].add_parser(
        "check", help="Vet survey runs and maps before a long job (images, files, timing, checksums).",
        description="Vet survey runs and maps: every image decoded strictly, every CSV/TOML/TUM file parsed, "
                    "timestamps, rates and gaps, every map file's checksum and format. One line per problem; "
                    "exit 0 when clean, 2 otherwise.")
    p.add_argument("paths", nargs="+", metavar="PATH", help="survey run, map, or a folder of them")
    p.add_argument("--max-gap", type=float, default=None, metavar="S",
                   help="longest tolerated interval between two images / odometry samples / INS poses "
                        "(default 1 s)")
    p.add_argument("--no-images", action="store_true", help="skip decoding the images (fast)")
    p.add_argument("--jobs", type=int, default=2, help="threads decoding images (default 2)")
    p.add_argument("--json", default=None, metavar="OUT", help="also write the result as JSON")
    p.set_defaults(_run=run)


def run(args) -> int:
    import json

    from scenesig.mapping.check import check_paths
    from scenesig.surveys.check import DEFAULT_MAX_GAP_S, Problem
    from scenesig.surveys.io import atomic_write_text

    max_gap = DEFAULT_MAX_GAP_S if args.max_gap is None else float(args.max_gap)
    result = check_paths(args.paths, max_gap_s=max_gap, images=not args.no_images, jobs=args.jobs,
                           progress=sys.stderr.isatty())
    for p in result["problems"]:
        print(Problem(**p))
    s = result["summary"]
    print(f"checked {s['runs']} runs ({s['images_checked']} images) and {s['maps']} maps "
          f"({s['places_checked']} places): {s['errors']} errors, {s['warnings']} warnings")
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1) + "\n")
    return 0 if s["errors"] == 0 else 2
