"""Cost and catch rate of strict image decoding: ``scenesig bench strict_decode [--json OUT]``.

Frames: simulated 640x480 views of one place of the demo world under nine conditions
(``scenesig.surveys.sim.place_views(preset="demo", seed=0)``), written as the simulator writes survey runs
(JPEG quality 95; and PNG).  Per frame, on one core, median over ``--repeats`` passes:

* ``lenient_ms`` -- ``cv2.imread`` of the file, what survey runs used before (decodes a truncated JPEG
  to a partly grey frame);
* ``strict_ms`` -- :func:`scenesig.surveys.images.read_image` (read the bytes, then libjpeg-turbo with every
  decoder warning an error; for PNG the chunk CRC/IEND walk, then OpenCV);
* ``overhead_ms`` -- median over frames of strict - lenient, timed back to back on each frame (the
  target is at most 1 ms per VGA frame; negative = strict is faster);

for colour (``bgr``) and gray decoding; for PNG also ``crc_walk_ms``, the strict check alone (the
decoding itself is OpenCV's either way).  Catch rates over ``--trials`` damaged copies of the frames:
``truncated`` (cut at a uniformly drawn byte after the headers) and ``bit_flip`` (one random bit of
the entropy-coded data flipped -- JPEG has no checksum, so a flip that still decodes to valid codes is
undetectable by any decoder; PNG's CRC catches every one): the share ``strict`` rejects and the share
``lenient`` (``cv2.imread`` returning None) rejects.  Seeds fixed.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from scenesig.surveys.errors import CorruptImageError
from scenesig.surveys.images import png_problem, read_image

__all__ = ["run_benchmark", "main"]


def _frames(n: int) -> tuple[list, str]:
    from scenesig.surveys.sim import place_views

    views = place_views(preset="demo", seed=0, n=n)
    return [np.asarray(v[0]) for v in views], "surveys.sim.place_views(preset='demo', seed=0)"


def _paired_ms(fns: dict, paths, repeats: int) -> dict:
    """Median ms per frame of each decoder, timed back to back on every frame (a loaded machine
    slows both alike); the per-frame difference's median is ``overhead_ms``."""
    per = {k: [] for k in fns}
    for _ in range(repeats):
        for p in paths:
            for k, fn in fns.items():
                t0 = time.perf_counter()
                fn(p)
                per[k].append(time.perf_counter() - t0)
    out = {f"{k}_ms": 1e3 * float(np.median(v)) for k, v in per.items()}
    out["overhead_ms"] = 1e3 * float(np.median(np.subtract(per["strict"], per["lenient"])))
    return out


def _catch(paths, kind: str, trials: int, rng) -> dict:
    strict = lenient = 0
    with tempfile.TemporaryDirectory() as tmp:
        bad = Path(tmp) / ("bad" + paths[0].suffix)
        for k in range(trials):
            data = bytearray(paths[k % len(paths)].read_bytes())
            lo = 1024 if len(data) > 4096 else len(data) // 4      # past the headers
            if kind == "truncated":
                data = data[: int(rng.integers(lo, len(data) - 2))]
            else:
                pos = int(rng.integers(lo, len(data) - 16))
                data[pos] ^= 1 << int(rng.integers(8))
            bad.write_bytes(bytes(data))
            try:
                read_image(bad)
            except CorruptImageError:
                strict += 1
            lenient += cv2.imread(str(bad), cv2.IMREAD_COLOR) is None
    return {"strict": strict / trials, "lenient": lenient / trials, "trials": trials}


def run_benchmark(n_frames: int = 18, repeats: int = 5, trials: int = 300) -> dict:
    cv2.setNumThreads(1)
    images, source = _frames(n_frames)
    rng = np.random.default_rng(0)
    out = {"frames": source, "n_frames": len(images), "size": [int(images[0].shape[1]), int(images[0].shape[0])],
           "repeats": repeats, "cpu_count": os.cpu_count(), "machine": platform.machine(), "formats": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for fmt, params in (("jpeg", [cv2.IMWRITE_JPEG_QUALITY, 95]), ("png", [])):
            ext = ".jpg" if fmt == "jpeg" else ".png"
            paths = []
            for i, img in enumerate(images):
                p = Path(tmp) / f"{i:03d}{ext}"
                cv2.imwrite(str(p), img, params)
                paths.append(p)
            res = {"bytes_mean": float(np.mean([p.stat().st_size for p in paths]))}
            for mode, flag, gray in (("bgr", cv2.IMREAD_COLOR, False), ("gray", cv2.IMREAD_GRAYSCALE, True)):
                res[mode] = _paired_ms({"lenient": lambda p: cv2.imread(str(p), flag),
                                        "strict": lambda p: read_image(p, gray)}, paths, repeats)
            if fmt == "png":     # the strict part alone: the chunk walk with every CRC
                blobs = [p.read_bytes() for p in paths]
                t0 = time.perf_counter()
                for _ in range(repeats):
                    for b in blobs:
                        png_problem(b)
                res["crc_walk_ms"] = 1e3 * (time.perf_counter() - t0) / (repeats * len(blobs))
            res["catch_rate"] = {k: _catch(paths, k, trials, rng) for k in ("truncated", "bit_flip")}
            out["formats"][fmt] = res
    jp = out["formats"]["jpeg"]
    out["overhead_ms_per_vga_frame"] = max(jp["bgr"]["overhead_ms"], jp["gray"]["overhead_ms"])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench strict_decode", description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=18, help="simulated frames (default 18)")
    ap.add_argument("--repeats", type=int, default=5, help="timing passes over the frames (default 5)")
    ap.add_argument("--trials", type=int, default=300, help="damaged copies per kind of damage (default 300)")
    ap.add_argument("--json", default=None, metavar="OUT", help="also write the JSON here")
    args = ap.parse_args(argv)
    res = run_benchmark(args.frames, args.repeats, args.trials)
    text = json.dumps(res, indent=1)
    print(text)
    if args.json:
        from scenesig.surveys.io import atomic_write_text

        atomic_write_text(args.json, text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
