"""The ``scenesig`` command line: one console script, one subcommand per pipeline stage.

Each subcommand's work lives in its stage's module as ``run_from_args(args) -> int``; this file only
declares arguments and imports the module when the subcommand runs, so ``scenesig --help`` stays
fast and a stage's heavy imports (GTSAM, Dask) are paid only by the stage that needs them.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from surveys.errors import DataError


def _positive_int(s: str) -> int:
    v = int(s)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="scenesig",
        description="Long-term visual localisation with scene signatures (McManus et al.).")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def cmd(name, target, help, parent=sub):
        sp = parent.add_parser(name, help=help, description=help)
        sp.set_defaults(_target=target)
        return sp

    s = cmd("simulate", "surveys.sim.simulate", "Render the simulated survey world as survey runs.")
    s.add_argument("out", help="output folder (one sub-folder per run)")
    s.add_argument("--preset", choices=["tiny", "demo", "begbroke"], default="demo")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--runs", default=None,
                   help="comma-separated conditions, one run each (default: the preset's list)")
    s.add_argument("--camera-hz", type=float, default=None, help="camera rate (default 20 Hz)")
    s.add_argument("--jobs", type=_positive_int, default=1, help="runs rendered in parallel")
    s.add_argument("--overwrite", action="store_true", help="replace runs already in OUT (default: refuse)")
    s.add_argument("--start-m", dest="start_m", type=float, default=0.0,
                   help="distance along the route (m) where every run begins (default 0); same world, same seed")

    b = sub.add_parser("bench", help="Benchmarks that print JSON.")
    bsub = b.add_subparsers(dest="bench", required=True, metavar="BENCH")
    h = cmd("heading", "signatures.heading_bench",
            "GRIEF heading-estimation benchmark (error rate at 20 px).", parent=bsub)
    h.add_argument("dataset", help="a GRIEF-layout folder (sessions + ground_truth/, or season_00/ + season_01/)")
    h.add_argument("--methods", default="signatures,orb,sift")
    h.add_argument("--json", required=True, help="output JSON file")
    h.add_argument("--figure", default=None, help="figure folder (default: beside the JSON)")
    h.add_argument("--jobs", type=_positive_int, default=2)
    h.add_argument("--baseline-preset", choices=["grief", "plain"], default="grief",
                   help="point-feature protocol: grief (published: 1600 upright keypoints, ratio 0.9, "
                        "20-px histogram voting) or plain (the data set README's reference settings)")
    h.add_argument("--max-pairs", type=_positive_int, default=None, help="only the first N pairs (quick look)")
    sp = cmd("speed", "signatures.speed_bench", "Training and detection speed on simulated images.", parent=bsub)
    sp.add_argument("--json", required=True, help="output JSON file")

    m = cmd("build-map", "mapping.build", "Build a map (a bank of scene signatures per place) from survey runs.")
    m.add_argument("runs", nargs="+", metavar="RUN", help="training survey runs")
    m.add_argument("--reference", required=True, metavar="RUN", help="the map run that defines places")
    m.add_argument("--out", required=True, help="map folder, e.g. maps/NAME")
    m.add_argument("--jobs", type=_positive_int, default=1, help="places built in parallel (joblib)")
    m.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://host:8786")

    ms = sub.add_parser("map", help="Inspect a map.")
    mss = ms.add_subparsers(dest="map_command", required=True, metavar="ACTION")
    show = cmd("show", "mapping.show", "Figures of a map: keyframes with signatures, a heat map.", parent=mss)
    show.add_argument("map", help="map folder")
    show.add_argument("--place", type=int, default=None, help="only this place")
    show.add_argument("--out", required=True, help="figure folder")

    lo = cmd("localise", "localiser.replay", "Localise a replayed traverse against a map.")
    lo.add_argument("map", help="map folder")
    lo.add_argument("run", help="survey run to replay")
    lo.add_argument("--method", choices=["signatures", "orb", "sift"], default="signatures")
    lo.add_argument("--out", required=True, help="output folder")
    mode = lo.add_mutually_exclusive_group()
    mode.add_argument("--every", type=_positive_int, default=4, help="detector on every N-th frame (deterministic)")
    mode.add_argument("--realtime", action="store_true", help="threads and queues, stale frames dropped")
    lo.add_argument("--speed", type=float, default=1.0,
                    help="with --realtime: replay speed as a multiple of the recorded rate (default 1)")
    lo.add_argument("--oracle", choices=["ins", "none"], default="ins",
                    help="ins (default, the paper's protocol): start and reset from the run's INS/GPS; none: no "
                         "INS/GPS -- global localisation from the map at start-up, relocalisation when lost")

    r = cmd("report", "localiser.report", "HTML report of localisation results.")
    r.add_argument("results", nargs="+", help="localise output folders or a demo folder")
    r.add_argument("--out", required=True)
    r.add_argument("--runs", nargs="*", default=None, metavar="RUN",
                   help="survey runs of the results (for speed and INS plots; found automatically when omitted)")

    d = cmd("demo", "localiser.demo", "The main job: simulate, build a map, localise, report.")
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.add_argument("--jobs", type=_positive_int, default=2, help="parallel workers (default 2)")
    d.add_argument("--preset", choices=["tiny", "demo", "begbroke"], default="demo",
                   help="simulated world (default demo, ≈300 m; tiny is a one-minute smoke run)")
    d.add_argument("--camera-hz", type=float, default=None,
                   help="camera rate of the simulated runs (default 10 Hz; the detector runs at 5 Hz either way)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    module = importlib.import_module(args._target)
    try:
        return int(module.run_from_args(args) or 0)
    except DataError as exc:
        print(f"scenesig: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("scenesig: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
