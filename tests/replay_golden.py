"""Digests of ``scenesig localise``'s outputs on the tiny world, to hold the replay's results fixed.

``tests/data/replay_golden.json`` holds the SHA-256 of ``trajectory.tum``, ``covariances.csv``,
``frames.csv`` and ``metrics.json`` (without its timing keys, the map's and the run's paths and the map's
random identity, which measure the machine, the folders and the build, not the result) of every method on the
night and overcast runs of the tiny world (``tests/build_world.py``).

History.  The digests first guarded the move of the per-frame step into
:class:`scenesig.localiser.session.Session`: they were recorded from the code *before* the move (325a86a,
then 433dc8c with main's later defaults patched in), another implementation than the one tested, and main
matched them byte for byte (the last time in CI at 8441525).  On another machine (an AMD EPYC with AVX2, no
AVX-512) the same code gave other bytes for every run that localises, under each OpenBLAS
kernel that CPU can run (Haswell, Zen, Sandybridge, Nehalem, Prescott).  A result's last bits depend on the
SIMD kernels the libraries pick for the CPU at hand (OpenBLAS's core type, numpy's and OpenCV's dispatched
loops, glibc's libm variants, numba's target), and on the night run a last bit can move a detection window
and so a detection (``OPENBLAS_CORETYPE`` alone, Haswell against Nehalem, moved the night ``signatures``
trajectory by up to 1.2 cm and changed a detection).  So
the digests are now made and checked in one pinned numerical environment, :data:`PORTABLE_ENV` (the x86-64
baseline kernels, one BLAS thread), in a process of their own that simulates, builds and localises the tiny
world from nothing; recorded from main (the commit the file names), they guard against any change of
results that is not intended, on whichever x86-64 CPU the suite runs.

Regenerate (only when a change of results is intended, and say so in the commit)::

    python tests/replay_golden.py BASE_FOLDER --record --commit SHA   # BASE_FOLDER gets tiny_runs/, tiny_map/, ...
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

GOLDEN = Path(__file__).resolve().parent / "data" / "replay_golden.json"

#: The numerical environment the digests are made in: every library held to the x86-64 baseline code paths
#: (SSE2/SSE3, which every x86-64 CPU runs) and to one BLAS thread (a sum split over threads is added in
#: another order), so the same wheels give the same bytes whatever the CPU offers beyond the baseline.
PORTABLE_ENV = {
    "OPENBLAS_CORETYPE": "Prescott",            # numpy's, scipy's and OpenCV's OpenBLAS: the generic kernels
    "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
    "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",   # numpy's dispatched loops
    "OPENCV_CPU_DISABLE": "SSE4.1,SSE4.2,AVX,FP16,AVX2,AVX512-SKX",      # OpenCV's dispatched loops
    "OPENCV_IPP": "disabled",                   # Intel IPP (its own dispatch)
    "NUMBA_CPU_NAME": "generic",                # the solver's and HOG's compiled loops
    "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX512F,-AVX2,-FMA,-AVX",       # libm's exp, log, pow, sin variants
    "JSIMD_FORCESSE2": "1",                     # libjpeg-turbo (bit-exact across its kernels by design)
}
# Measured on an AVX2 CPU, each left native alone: OpenBLAS's kernel, OpenCV's loops and libm's variants each
# changed the digests (32, 24 and 27 of 48); numpy's loops, the thread counts, IPP and numba's target did not
# there (they may on a CPU with AVX-512).  onnxruntime's kernels (XFeat: the heavy cases' xfeat-all only) have
# no such switch, so those two digests may still differ on a CPU with other vector units.

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


def portable_digests(base: Path, which: str) -> dict:
    """The digests of the cases ``which`` (``"cases"`` or ``"heavy_cases"``), made from nothing under
    ``base`` by a process of their own in :data:`PORTABLE_ENV`."""
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), str(base), "--print", which],
                          env={**os.environ, **PORTABLE_ENV}, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"replay_golden.py {base} --print {which} failed ({proc.returncode}):\n"
                           f"{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _digests(base: Path, which: str) -> dict:
    from build_world import tiny_map

    if which == "cases":
        return replay_digests(tiny_map(base), base, base / "out", CASES)
    if which == "heavy_cases":
        return replay_digests(golden_map(base), base, base / "out_heavy", HEAVY_CASES)
    raise ValueError(f"unknown case set {which!r} (cases, heavy_cases)")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    base = Path(argv[0])
    if "--print" in argv:                       # one case set's digests as one JSON line (portable_digests)
        if any(os.environ.get(k) != v for k, v in PORTABLE_ENV.items()):
            raise SystemExit("replay_golden.py --print runs in PORTABLE_ENV (use portable_digests)")
        print(json.dumps(_digests(base, argv[argv.index("--print") + 1])))
        return 0
    if "--record" not in argv:
        raise SystemExit("usage: replay_golden.py BASE_FOLDER --record --commit SHA")
    commit = argv[argv.index("--commit") + 1] if "--commit" in argv else "unknown"   # the code that recorded
    golden = {"commit": commit, "environment": PORTABLE_ENV,
              "cases": portable_digests(base, "cases"), "heavy_cases": portable_digests(base, "heavy_cases")}
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps(golden, indent=2) + "\n")
    print(json.dumps(golden, indent=2))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    raise SystemExit(main())
