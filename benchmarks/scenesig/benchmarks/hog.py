"""HOG benchmark: one level and a pyramid on one image (default: a random 640x480 texture):
``scenesig bench hog [IMAGE]``.
"""
from __future__ import annotations

import argparse
import json

import cv2
import numpy as np

from scenesig.benchmarks._timing import median_ms
from scenesig.signatures.hog import build_pyramid, fhog
from scenesig.surveys.errors import DataError

__all__ = ["main"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench hog", description="Time the HOG level and pyramid on one image.")
    ap.add_argument("image", nargs="?", help="image file (default: random 640x480 texture)")
    ap.add_argument("--levels", type=int, default=9, help="pyramid levels 0..N-1")
    args = ap.parse_args(argv)
    if args.image:
        img = cv2.imread(args.image, cv2.IMREAD_COLOR)
        if img is None:
            raise DataError(args.image, "cannot read or decode image")
    else:
        rng = np.random.default_rng(0)
        img = cv2.GaussianBlur(rng.integers(0, 255, (480, 640), dtype=np.uint8), (5, 5), 1.5)
    print(json.dumps({
        "image": list(img.shape[:2]),
        "hog_ms_per_level": round(median_ms(lambda: fhog(img)), 2),
        "hog_pyramid_ms": round(median_ms(lambda: build_pyramid(img, levels=range(args.levels))), 2),
        "levels": args.levels,
    }))
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "hog", *sys.argv[1:]]))
