"""Shared fixtures: the real data location, and small synthetic survey runs."""
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
SHARED_MODELS = ROOT.parent / "shared" / "models"


@pytest.fixture(autouse=True)
def _library_thread_section():
    """An in-process command-line call (``main([...])``) installs the runtime layer's process-wide OpenCV
    tuning around the library's threads (:func:`scenesig.runtime.configure`); later tests of the library
    itself must see the library's own default again, whatever order they run in."""
    from scenesig.signatures import hog

    before = hog._PARALLEL_SECTION
    yield
    hog.set_parallel_section(before)


@pytest.fixture
def grief_root():
    """``../shared/data/grief``; skips with a message where the real data is absent."""
    path = SHARED_DATA / "grief"
    if not path.is_dir():
        pytest.skip(f"real data not found at {path} (tests on GRIEF need ../shared/data beside the project)")
    return path


@pytest.fixture
def xfeat_model():
    """``../shared/models/xfeat/xfeat.onnx`` (and onnxruntime); skips with a message where either is absent."""
    path = SHARED_MODELS / "xfeat" / "xfeat.onnx"
    if not path.is_file():
        pytest.skip(f"XFeat model not found at {path} (tests of learned features need ../shared/models "
                    f"beside the project)")
    pytest.importorskip("onnxruntime", reason="XFeat needs onnxruntime (pip install 'scenesig[learned]')")
    return path


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory):
    """The tiny simulated world of ``tests/build_world.py``: ``(runs, map folder)``, built once per session
    folder (the map is reused from disk)."""
    from build_world import tiny_map, tiny_runs

    base = tmp_path_factory.getbasetemp()
    return tiny_runs(base), tiny_map(base)


def make_run(n_frames=5, with_truth=True, size=(64, 48), seed=0):
    """A small synthetic SurveyRun (in memory) and its images."""
    from scenesig.surveys.geometry import CAMERA_FROM_VEHICLE_AXES, Camera, make_pose, rot_z
    from scenesig.surveys.run import SurveyRun

    rng = np.random.default_rng(seed)
    w, h = size
    cam = Camera(50.0, 50.0, w / 2 - 0.5, h / 2 - 0.5, w, h)
    t = np.arange(n_frames) * 0.05
    poses = np.stack([make_pose(rot_z(0.01 * k), [0.5 * k, 0.1 * np.sin(k), 0.0]) for k in range(n_frames)])
    run = SurveyRun(
        name="synthetic", conditions=["sunny"], camera=cam,
        T_vehicle_camera=make_pose(CAMERA_FROM_VEHICLE_AXES, [0, 0, 1.5]),
        rates={"camera_hz": 20.0, "odometry_hz": 20.0, "ins_hz": 20.0},
        frame_times=t, frame_files=[f"images/{i:06d}.png" for i in range(n_frames)],
        odometry_times=t, odometry_poses=poses, groundtruth_times=t, groundtruth_poses=poses,
        truth_times=t if with_truth else None, truth_poses=poses if with_truth else None,
        gps=np.column_stack([t, poses[:, :3, 3]]), metadata={"seed": seed},
    )
    images = [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in range(n_frames)]
    return run, images


# Property-based fuzzing (tests/test_fuzz_readers.py).  Two hypothesis profiles: "scenesig-fuzz" keeps
# the default suite fast; "scenesig-fuzz-heavy" runs many more examples -- the tests marked heavy use
# it, and SCENESIG_FUZZ=heavy makes the default fuzz tests use it too.  Both are derandomized (a
# fixed seed: a failure repeats) and keep no example database.
try:
    from hypothesis import HealthCheck, settings

    FUZZ_EXAMPLES = {"scenesig-fuzz": 40, "scenesig-fuzz-heavy": 2000}
    for _name, _n in FUZZ_EXAMPLES.items():
        settings.register_profile(_name, max_examples=_n, deadline=None, derandomize=True, database=None,
                                  suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
except ImportError:  # hypothesis is a test extra; test_fuzz_readers.py says it is missing
    FUZZ_EXAMPLES = {}
