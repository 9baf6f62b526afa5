"""Simulated fixed webcams: ``scenesig bench simcam OUT [--places N]`` writes a webcam-layout folder.

A development set for single-experience settings that shares no image with the reported data sets
(the real webcams, GRIEF): ``N`` places of the embedded simulator's demo world (seed 0), each
rendered from one unjittered camera pose -- a fixed camera, so the truth is the identity as on the
real webcams -- under ten conditions, with the file names ``scenesig bench webcam`` reads
(``YYYYMMDD_HHMMSS.png``, sorted = by time, hour = period).  Sorted by name, the even positions are
sunny noon (``--train single`` trains on it), morning, overcast, autumn and overcast; the odd ones,
the test images, are night (23 h), fog, snow, dusk (20 h) and rain::

    scenesig bench simcam /tmp/simcam
    scenesig bench webcam /tmp/simcam --train single --json dev.json

Prints a JSON summary (folder, places, route positions, files per condition).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from scenesig.benchmarks._stages import emit_json

__all__ = ["SCHEDULE", "render_folder", "main"]

#: (file stem, condition): sorted by name, even positions train (multi), odd ones are tested.
SCHEDULE = (
    ("20200101_120000", "sunny"),
    ("20200102_230000", "night"),
    ("20200103_080000", "morning"),
    ("20200104_090000", "fog"),
    ("20200105_130000", "overcast"),
    ("20200106_110000", "snow"),
    ("20200107_150000", "autumn"),
    ("20200108_200000", "dusk"),
    ("20200109_160000", "overcast"),
    ("20200110_140000", "rain"),
)


def render_folder(out, places: int = 6, seed: int = 0, size=(640, 480)) -> dict:
    """Render the folder (module docstring); returns the summary."""
    from scenesig.surveys.io import atomic_path
    from scenesig.surveys.sim.views import get_world, place_views_with_poses

    world = get_world("demo", seed)
    L = float(world.route.drive_length)
    out = Path(out)
    positions = [L * (0.1 + 0.8 * k / max(1, places - 1)) for k in range(places)]
    conds = [c for _, c in SCHEDULE]
    for k, s in enumerate(positions):
        views = place_views_with_poses("demo", seed, n=len(SCHEDULE), s=s, size=size,
                                       conditions=conds, jitter=False)
        d = out / f"place{k:02d}"
        d.mkdir(parents=True, exist_ok=True)
        for (stem, cond), v in zip(SCHEDULE, views):
            assert v["condition"] == cond
            with atomic_path(d / f"{stem}.png") as tmp:
                if not cv2.imwrite(str(tmp), v["image"]):
                    raise OSError(f"cannot write {tmp}")
    return {"folder": str(out), "places": places, "seed": seed, "route_positions_m": positions,
            "image_size": list(size), "files": {stem: cond for stem, cond in SCHEDULE}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench simcam", description=__doc__.splitlines()[0])
    ap.add_argument("out", help="folder to write (one sub-folder per place)")
    ap.add_argument("--places", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="write the summary JSON here")
    args = ap.parse_args(argv)
    emit_json(render_folder(args.out, args.places, args.seed), args.json)
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "simcam", *sys.argv[1:]]))
