"""``scenesig report RESULTS... --out DIR``: HTML report of localisation results."""
from __future__ import annotations


def register(groups):
    help = "HTML report of localisation results."
    p = groups[""].add_parser("report", help=help, description=help)
    p.add_argument("results", nargs="+", help="localise output folders or a demo folder")
    p.add_argument("--out", required=True)
    p.add_argument("--runs", nargs="*", default=None, metavar="RUN",
                   help="survey runs of the results (for speed and INS plots; found automatically when omitted)")
    p.set_defaults(_run=run)


def run(args) -> int:
    from scenesig.report import build_report

    index = build_report(args.results, args.out, runs=args.runs or None)
    print(f"report: {index}")
    return 0
