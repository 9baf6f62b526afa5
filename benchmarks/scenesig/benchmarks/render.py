"""Rendering speed benchmark: frames per second on one core, per condition.

``scenesig bench render --preset demo --frames 300`` drives a lap's worth of poses through the
preset's world and reports rendered frames/s (texture baking included: it is part of a real run) and
with JPEG encoding (quality 95, as written to disk).  OpenCV is limited to one thread.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from scenesig.surveys.io import atomic_write_text
from scenesig.surveys.sim.conditions import CONDITIONS
from scenesig.surveys.sim.motion import plan_drive
from scenesig.surveys.sim.noise import rng_for
from scenesig.surveys.sim.scene import RunScene, default_extrinsic
from scenesig.surveys.sim.views import get_world

__all__ = ["benchmark", "main"]


def benchmark(preset: str = "demo", seed: int = 0, frames: int = 300, conditions=None, threads: int = 1) -> dict:
    """Frames/s of :meth:`RunScene.render` along a planned drive (frame poses at 20 Hz)."""
    cv2.setNumThreads(threads)
    world = get_world(preset, seed)
    drive = plan_drive(world.route, rng_for(seed, "bench"), world.crossings)
    t = np.linspace(1.0, drive.duration - 1.0, frames)
    P = drive.pose(t) @ default_extrinsic()
    v = drive.speed(t)
    out = {"preset": preset, "size": list(world.image_size), "frames": frames, "threads": threads, "conditions": {}}
    for c in conditions or list(CONDITIONS):
        t0 = time.perf_counter()
        scene = RunScene(world, c, run_key=("bench",))
        t_setup = time.perf_counter() - t0
        t_render = t_jpeg = 0.0
        for k in range(frames):
            a = time.perf_counter()
            img, _ = scene.render(P[k], frame=k, velocity=(float(v[k]), 0.0))
            b = time.perf_counter()
            cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
            t_render += b - a
            t_jpeg += time.perf_counter() - b
        out["conditions"][c] = {"render_fps": round(frames / (t_render + t_setup), 1),
                                "with_jpeg_fps": round(frames / (t_render + t_setup + t_jpeg), 1),
                                "setup_s": round(t_setup, 2)}
    fps = [r["render_fps"] for r in out["conditions"].values()]
    out["render_fps_mean"] = round(float(len(fps) / np.sum(1 / np.array(fps))), 1)  # harmonic: time-weighted
    jf = [r["with_jpeg_fps"] for r in out["conditions"].values()]
    out["with_jpeg_fps_mean"] = round(float(len(jf) / np.sum(1 / np.array(jf))), 1)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scenesig bench render", description=__doc__.split("\n")[0])
    p.add_argument("--preset", default="demo")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--conditions", default=None, help="comma list (default: all)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default=None, help="also write the JSON to this file")
    a = p.parse_args(argv)
    res = benchmark(a.preset, a.seed, a.frames, a.conditions.split(",") if a.conditions else None, a.threads)
    # the table for people on stderr, the JSON alone on stdout (so it can be piped)
    for c, r in res["conditions"].items():
        print(f"{c:9s} render {r['render_fps']:6.1f} frames/s   with JPEG {r['with_jpeg_fps']:6.1f} frames/s",
              file=sys.stderr)
    print(f"all       render {res['render_fps_mean']:6.1f} frames/s   with JPEG {res['with_jpeg_fps_mean']:6.1f} frames/s "
          f"({res['size'][0]}x{res['size'][1]}, {res['threads']} thread)", file=sys.stderr)
    text = json.dumps(res)
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.json, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "render", *sys.argv[1:]]))
