"""The demo's localisation stage on a finished demo: ``scenesig bench demo_localise DEMO_DIR --out DIR``.

Localises every live run of ``DEMO_DIR`` (a ``scenesig demo`` output) with every demo entry, and runs
the matching experiment, exactly as the demo's stage 3 does (:func:`scenesig.demo.localise_live_runs`),
against ``DEMO_DIR/map`` (read only), writing into ``DIR`` (emptied first; never inside ``DEMO_DIR``).
Prints JSON: the stage's wall time, the CPU time of this process and its pool workers (on a shared
machine compare CPU: wall time includes waiting for a core), the load average, and per entry the
replays' summed ``wall_seconds``; with ``--compare`` it also checks that every localisation output
equals ``DEMO_DIR/localise``'s apart from timing keys and paths.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

__all__ = ["benchmark", "main"]

#: metrics.json keys that may differ between two runs of the same code (timings, where it ran)
_VOLATILE = {"ms_per_detection", "ms_per_solve", "ms_per_odometry_update", "ms_per_retrieval", "realtime_factor",
             "wall_seconds", "cpu_seconds", "cpu_ms_per_frame", "run_path", "map"}


def _cpu_seconds() -> float:
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in [me] + me.children(recursive=True):
        try:
            t = p.cpu_times()
        except psutil.Error:          # a worker that exited meanwhile
            continue
        total += t.user + t.system
    return total


def _same_outputs(a: Path, b: Path) -> bool:
    for name in ("frames.csv", "trajectory.tum"):
        if (a / name).read_bytes() != (b / name).read_bytes():
            return False
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    return {k: v for k, v in ma.items() if k not in _VOLATILE} == {k: v for k, v in mb.items() if k not in _VOLATILE}


def benchmark(demo_dir, out, jobs: int = 2, compare: bool = False) -> dict:
    """Run the demo's localisation stage of ``demo_dir`` into ``out``; see the module docstring."""
    from scenesig.demo import default_config, localise_live_runs

    demo_dir, out = Path(demo_dir).resolve(), Path(out).resolve()
    if out == demo_dir or demo_dir in out.parents:
        raise ValueError(f"--out {out} must not be inside the demo folder {demo_dir}")
    summary = json.loads((demo_dir / "summary.json").read_text())
    cfg = {**default_config, **summary.get("config", {})}
    every = round(float(cfg["camera_hz"]) / float(cfg["detector_hz"]))
    live = [r["run"] for r in summary["runs"]]
    names = [r["name"] for r in json.loads((demo_dir / "world" / "simulate_summary.json").read_text())["runs"]]
    reference = names[list(cfg["training"]).index(cfg["reference"])]
    entries = list(cfg["methods"]) + [f"{m}-none" for m in cfg["no_oracle_methods"]]
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    cpu0, t0 = _cpu_seconds(), time.perf_counter()
    metrics, matching = localise_live_runs(demo_dir / "map", demo_dir / "world", out, live, reference, entries,
                                           every, jobs, progress=False)
    wall, cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
    res = {"demo": str(demo_dir), "jobs": int(jobs), "cpu_count": os.cpu_count(), "wall_seconds": wall,
           "cpu_seconds": cpu, "load_average": list(os.getloadavg()), "live_runs": live, "entries": entries,
           "replay_wall_seconds_by_entry": {e: float(sum(metrics[(n, e)].get("wall_seconds") or 0.0 for n in live))
                                            for e in entries},
           "matching_places": len(matching.places)}
    if compare:
        differ = [f"{n}/{e}" for n in live for e in entries
                  if not _same_outputs(demo_dir / "localise" / n / e, out / n / e)]
        res["identical_to_demo"] = not differ
        res["different"] = differ
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench demo_localise",
                                 description="The demo's localisation stage (every live run and entry, and the "
                                             "matching experiment) on a finished demo: wall and CPU time.")
    ap.add_argument("demo", help="a scenesig demo output folder (with world/, map/, summary.json)")
    ap.add_argument("--out", required=True, help="folder for the localisations (emptied first)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--compare", action="store_true", help="check the outputs equal the demo's own localisations")
    ap.add_argument("--json", help="also write the JSON here")
    args = ap.parse_args(argv)
    res = benchmark(args.demo, args.out, args.jobs, args.compare)
    text = json.dumps(res, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "demo_localise", *sys.argv[1:]]))
