"""Digests of ``scenesig localise``'s outputs on the tiny world, to hold the replay byte-identical.

``tests/data/replay_golden.json`` holds the SHA-256 of ``trajectory.tum``, ``covariances.csv``,
``frames.csv`` and ``metrics.json`` (without its timing keys, the map's and the run's paths and the map's
random identity, which measure the machine, the folders and the build, not the result) of every method on the
night and overcast runs of the tiny world (``tests/build_world.py``), recorded from the commit the file names
(433dc8c: main with the integrity monitor's sequential test, the replay as it was *before* it became a driver
over :class:`scenesig.localiser.session.Session`; first recorded from 325a86a, re-recorded when the integrity
work changed the alerts on purpose, again with the defaults re-chosen on twelve calibration worlds patched
into 433dc8c's two constants -- ``INFLATION`` and the monitor's ``sprt_dispersion`` / ``cusum_h`` -- and again
when the monitor's evidence became the solver's inliers on every frame and its defaults were re-chosen: those
four settings and the two lines that count a frame's fired signatures patched in; on the tiny world only
``metrics.json`` changed, through the settings it records; and again when the stated covariance gained the
innovation term, with ``INFLATION`` 2.15 and the term -- the localiser's innovation record and the two lines
adding it to the covariance -- patched in: bounds and covariances changed, trajectories did not).  The
recording is another implementation than the one tested, so a match says the refactor changed no byte.
Digests hold on the machine that recorded them (the same libraries); elsewhere regenerate from the recording commit.

Regenerate (only when a change of results is intended, and say so in the commit), with the recording
commit's code on ``PYTHONPATH`` (``git worktree add DIR SHA``)::

    python tests/replay_golden.py BASE_FOLDER [--commit SHA]  # BASE_FOLDER gets tiny_runs/, tiny_map/, golden_map/
"""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

GOLDEN = Path(__file__).resolve().parent / "data" / "replay_golden.json"

#: (case name, run's condition, method, oracle, every) replayed on the default tiny map (layers signatures,
#: orb, orb-all): the night run fails and alerts often (the failure rule, the integrity monitor), the
#: overcast run localises (and, without INS/GPS, finds itself by global search)
CASES = [("signatures", "night", "signatures", "ins", 4), ("signatures-every2", "night", "signatures", "ins", 2),
         ("orb", "night", "orb", "ins", 4), ("orb-all", "night", "orb-all", "ins", 4),
         ("hybrid-orb", "night", "hybrid-orb", "ins", 4), ("hybrid-orb-all", "night", "hybrid-orb-all", "ins", 4),
         ("signatures-none", "night", "signatures", "none", 2), ("orb-none", "night", "orb", "none", 2),
         ("overcast-signatures", "overcast", "signatures", "ins", 4),
         ("overcast-signatures-none", "overcast", "signatures", "none", 1),
         ("overcast-orb-none", "overcast", "orb", "none", 1),
         ("overcast-hybrid-orb", "overcast", "hybrid-orb", "ins", 2)]
#: ... and on the tiny map with every point layer (built for the heavy test: ``golden_map``)
HEAVY_LAYERS = ["signatures", "orb", "sift", "orb-all", "sift-all", "xfeat-all"]
HEAVY_CASES = [("sift", "night", "sift", "ins", 4), ("sift-all", "night", "sift-all", "ins", 4),
               ("hybrid", "night", "hybrid", "ins", 4), ("hybrid-sift-all", "night", "hybrid-sift-all", "ins", 4),
               ("xfeat-all", "night", "xfeat-all", "ins", 4), ("overcast-hybrid", "overcast", "hybrid", "ins", 4),
               ("overcast-xfeat-all", "overcast", "xfeat-all", "ins", 4)]


def output_digests(folder: Path) -> dict:
    """SHA-256 of the result files of a localise output folder (metrics.json without its timings)."""
    from scenesig.localiser.outputs import TIMING_KEYS

    folder = Path(folder)
    out = {name: hashlib.sha256((folder / name).read_bytes()).hexdigest()
           for name in ("trajectory.tum", "covariances.csv", "frames.csv")}
    metrics = json.loads((folder / "metrics.json").read_text())
    for k in (*TIMING_KEYS, "map", "run_path", "map_id"):      # the machine, the folders, the build's identity
        metrics.pop(k, None)
    out["metrics.json"] = hashlib.sha256(json.dumps(metrics, sort_keys=True).encode()).hexdigest()
    return out


def replay_digests(map_root: Path, base: Path, out: Path, cases) -> dict:
    """``{case: digests}`` of each case replayed with :func:`scenesig.localiser.replay.localise` on the tiny
    world's runs under ``base``."""
    from scenesig.localiser.replay import localise

    found = {}
    for name, condition, method, oracle, every in cases:
        folder = Path(out) / name
        localise(map_root, tiny_run(base, condition).root, folder, method=method, every=every, oracle=oracle,
                 progress=False, figure=False)
        found[name] = output_digests(folder)
    return found


def golden_map(base: Path) -> Path:
    """The tiny world's reference map with every point layer (built on first use into ``base/golden_map``)."""
    from build_world import CONFIG, tiny_runs

    from scenesig.mapping.build import build_map

    runs = tiny_runs(base)
    root = Path(base) / "golden_map"
    if not (root / "build_summary.json").exists():
        build_map(runs, runs[0], root, jobs=2, progress=False, config={**CONFIG, "layers": HEAVY_LAYERS})
    return root


def tiny_run(base: Path, condition: str):
    """The tiny world's run in ``condition`` (sunny: the reference, overcast, night)."""
    from build_world import tiny_runs

    return next(r for r in tiny_runs(base) if r.conditions[0] == condition)


def main(argv=None) -> int:
    from build_world import tiny_map

    argv = sys.argv[1:] if argv is None else argv
    base = Path(argv[0])
    commit = argv[argv.index("--commit") + 1] if "--commit" in argv else "unknown"   # the code that recorded
    if "--digest-only" in argv:        # the output folders are already there (written by the recorded commit)
        golden = {"commit": commit,
                  "cases": {c[0]: output_digests(base / "out" / c[0]) for c in CASES},
                  "heavy_cases": {c[0]: output_digests(base / "out_heavy" / c[0]) for c in HEAVY_CASES}}
    else:
        golden = {"commit": commit,
                  "cases": replay_digests(tiny_map(base), base, base / "out", CASES),
                  "heavy_cases": replay_digests(golden_map(base), base, base / "out_heavy", HEAVY_CASES)}
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps(golden, indent=2) + "\n")
    print(json.dumps(golden, indent=2))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    raise SystemExit(main())
