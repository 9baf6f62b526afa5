"""Mining benchmark: mine scene signatures for one place from aligned images (offsets assumed zero) and
print the mining statistics (McManus et al. 2015, §3.1): ``scenesig bench mining IMAGE... [--out BANK.npz]``.
"""
from __future__ import annotations

import argparse
import json

import cv2
import numpy as np

from scenesig.signatures.mining import mine_place
from scenesig.surveys.errors import DataError

__all__ = ["main", "read_images"]


def read_images(paths) -> list:
    """BGR images from files; DataError naming the first that cannot be read."""
    imgs = []
    for p in paths:
        im = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if im is None:
            raise DataError(p, "cannot read or decode image")
        imgs.append(im)
    return imgs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench mining",
                                 description="Mine scene signatures for one place from a folder of aligned images "
                                             "(offsets assumed zero).")
    ap.add_argument("images", nargs="+", help="image files of one place")
    ap.add_argument("--out", help="write the bank arrays to this .npz")
    ap.add_argument("--n-jobs", type=int, default=1)
    args = ap.parse_args(argv)
    bank, stats = mine_place(read_images(args.images), n_jobs=args.n_jobs, progress=True)
    if args.out:
        np.savez_compressed(args.out, **bank.to_arrays())
    print(json.dumps(stats.as_dict()))
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "mining", *sys.argv[1:]]))
