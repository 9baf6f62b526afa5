"""Import speed of a KITTI raw drive (decode + write), one core: prints JSON.

    python -m scenesig.benchmarks.kitti_import [DRIVE_DIR] [--camera 2] [--repeats 3] [--json OUT]

Each repeat imports the drive into a fresh temporary run (every image decoded once to check it,
OXTS and calibration parsed, the run written atomically) with the process pinned to one CPU and
OpenCV single-threaded. Reports the best repeat's wall-clock ``frames_per_second`` and, because a
shared machine steals wall time, ``frames_per_cpu_second`` (frames over the process's CPU time), with
the load average at the start.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_DRIVE = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "kitti" / "2011_09_26_snippet"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m scenesig.benchmarks.kitti_import", description=__doc__.splitlines()[0])
    ap.add_argument("drive", nargs="?", default=str(DEFAULT_DRIVE), help="KITTI raw drive (default: the shared snippet)")
    ap.add_argument("--camera", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None, help="also write the JSON here")
    args = ap.parse_args(argv)
    drive = Path(args.drive)
    if not drive.is_dir():
        print(f"kitti_import: drive not found: {drive} (the shared data is expected at ../shared/data)", file=sys.stderr)
        return 2
    import cv2

    from scenesig.surveys.importers.kitti_raw import import_kitti_raw

    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    best = None
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            out = Path(tmp) / f"run{r}"
            w0, c0 = time.perf_counter(), time.process_time()
            import_kitti_raw(drive, out, {"camera": args.camera}, progress=False)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            frames = sum(1 for _ in (out / "images").iterdir())
            if best is None or wall < best[0]:
                best = (wall, cpu, frames)
    wall, cpu, frames = best
    result = {"benchmark": "kitti_import", "drive": str(drive.resolve()), "camera": args.camera, "frames": frames,
              "seconds": round(wall, 3), "frames_per_second": round(frames / wall, 1),
              "cpu_seconds": round(cpu, 3), "frames_per_cpu_second": round(frames / cpu, 1),
              "repeats": args.repeats, "threads": 1, "load_average_1min": load,
              "target_frames_per_second": 50}
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        from scenesig.surveys.io import atomic_write_text

        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.json, text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
