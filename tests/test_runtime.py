"""Process-wide tuning belongs to the command line (scenesig.runtime), not to importing or calling the library."""
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_PROBE = """
import json, os, sys, threading
import cv2
before = {"cv": cv2.getNumThreads(), "env": os.environ.get("MALLOC_MMAP_THRESHOLD_")}
import numpy as np
import scenesig.signatures.hog, scenesig.signatures.bank, scenesig.mapping.build, scenesig.localiser.replay
from scenesig.signatures.hog import build_pyramid
build_pyramid(np.random.default_rng(0).integers(0, 255, (96, 128), dtype=np.uint8), threads=2)
after = {"cv": cv2.getNumThreads(), "env": os.environ.get("MALLOC_MMAP_THRESHOLD_"),
         "threads": threading.active_count()}
if sys.argv[1] == "cli":
    from scenesig.runtime import configure
    configure()
configured = {"cv": cv2.getNumThreads(), "env": os.environ.get("MALLOC_MMAP_THRESHOLD_")}
print(json.dumps({"before": before, "after": after, "configured": configured}))
"""


def _probe(mode):
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "SCENESIG_NO_MALLOPT"}
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], cwd=ROOT, env=env, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_and_calling_the_library_changes_no_process_state():
    r = _probe("library")
    assert r["after"]["cv"] == r["before"]["cv"]          # OpenCV's threads untouched
    assert r["after"]["env"] is None                       # no malloc tuning
    assert r["after"]["threads"] == 1                      # no pool threads left behind
    assert r["configured"] == {k: r["after"][k] for k in ("cv", "env")}


def test_the_command_line_runtime_tunes_malloc_for_itself_and_its_workers():
    r = _probe("cli")
    if not sys.platform.startswith("linux"):
        return
    assert r["configured"]["env"] == str(64 << 20)        # inherited by the worker processes it starts
    assert r["configured"]["cv"] == r["before"]["cv"]      # OpenCV changes only inside threaded sections
