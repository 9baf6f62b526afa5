"""Survey-run format: round trip, and every kind of bad input named by file and line."""
import numpy as np
import pytest
from conftest import make_run

from scenesig.surveys.errors import DataError
from scenesig.surveys.run import read_run, write_run
from scenesig.surveys.tum import read_tum, write_tum


@pytest.fixture
def run_dir(tmp_path):
    run, images = make_run()
    return write_run(run, tmp_path / "run", images=images), run, images


def test_round_trip_is_identical(run_dir, tmp_path):
    folder, run, images = run_dir
    back = read_run(folder)
    assert back.name == run.name and back.conditions == run.conditions
    assert back.camera == run.camera and back.rates == run.rates and back.metadata == run.metadata
    np.testing.assert_allclose(back.frame_times, run.frame_times, rtol=0, atol=1e-9)  # stored to the ns
    np.testing.assert_allclose(back.odometry_poses, run.odometry_poses, atol=1e-12)
    np.testing.assert_allclose(back.truth_poses, run.truth_poses, atol=1e-12)
    np.testing.assert_allclose(back.gps, run.gps, rtol=0, atol=1e-9)
    for i, img in enumerate(images):  # PNG is lossless
        np.testing.assert_array_equal(back.image(i), img)
    # written again from what was read: byte-identical files
    again = write_run(back, tmp_path / "again")
    for f in sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file()):
        assert (again / f).read_bytes() == (folder / f).read_bytes(), f


def test_write_refuses_to_clobber_and_is_atomic(run_dir):
    folder, run, images = run_dir
    with pytest.raises(FileExistsError):
        write_run(run, folder, images=images)

    def broken():
        yield images[0]
        raise RuntimeError("renderer died")

    with pytest.raises(RuntimeError):
        write_run(run, folder, images=broken(), overwrite=True)
    read_run(folder)  # the old run is intact


def _expect(folder, fname, line, fragment):
    with pytest.raises(DataError) as err:
        read_run(folder)
    assert err.value.path.name == fname, str(err.value)
    assert err.value.line == line, str(err.value)
    assert fragment in str(err.value)


def _edit(path, old, new):
    path.write_text(path.read_text().replace(old, new, 1))


def test_unsorted_frame_timestamps(run_dir):
    folder, *_ = run_dir
    lines = (folder / "frames.csv").read_text().splitlines()
    lines[2], lines[3] = lines[3].split(",")[0] + "," + lines[2].split(",")[1], lines[2].split(",")[0] + "," + lines[3].split(",")[1]
    (folder / "frames.csv").write_text("\n".join(lines) + "\n")
    _expect(folder, "frames.csv", 4, "strictly increase")


def test_nan_in_odometry(run_dir):
    folder, *_ = run_dir
    lines = (folder / "odometry.csv").read_text().splitlines()
    parts = lines[3].split(",")
    parts[2] = "nan"
    lines[3] = ",".join(parts)
    (folder / "odometry.csv").write_text("\n".join(lines) + "\n")
    _expect(folder, "odometry.csv", 4, "NaN")


def test_non_numeric_and_wrong_columns(run_dir):
    folder, *_ = run_dir
    p = folder / "odometry.csv"
    good = p.read_text()
    lines = good.splitlines()
    lines[2] = "abc" + lines[2][lines[2].index(","):]
    p.write_text("\n".join(lines) + "\n")
    _expect(folder, "odometry.csv", 3, "non-numeric")
    lines = good.splitlines()
    lines[5] = lines[5] + ",1.0"
    p.write_text("\n".join(lines) + "\n")
    _expect(folder, "odometry.csv", 6, "columns")


def test_missing_and_corrupt_image(run_dir):
    folder, *_ = run_dir
    (folder / "images" / "000002.png").write_bytes(b"garbage")
    _expect(folder, "frames.csv", 4, "not a JPEG or PNG")
    (folder / "images" / "000002.png").unlink()
    _expect(folder, "frames.csv", 4, "missing")


def test_truncated_image_fails_when_loaded(run_dir):
    folder, *_ = run_dir
    p = folder / "images" / "000003.png"
    p.write_bytes(p.read_bytes()[:20])
    run = read_run(folder)  # header still looks like PNG; decoding happens lazily
    with pytest.raises(DataError, match="000003.png"):
        run.image(3)


def test_bad_tum(run_dir):
    folder, *_ = run_dir
    p = folder / "groundtruth.tum"
    lines = p.read_text().splitlines()
    lines[1] = lines[1] + " 7"
    p.write_text("\n".join(lines) + "\n")
    _expect(folder, "groundtruth.tum", 2, "8 columns")


def test_bad_run_toml(run_dir):
    folder, *_ = run_dir
    p = folder / "run.toml"
    good = p.read_text()
    _edit(p, "format_version = 1", "format_version = 99")
    _expect(folder, "run.toml", None, "format_version 99")
    p.write_text(good.replace("fx = ", "fx = -"))
    _expect(folder, "run.toml", None, "camera.fx")
    p.write_text(good + "\n[[[broken")
    _expect(folder, "run.toml", None, "not valid TOML")
    (folder / "run.toml").unlink()
    _expect(folder, "run.toml", None, "not found")


def test_wrong_image_size(run_dir):
    folder, *_ = run_dir
    _edit(folder / "run.toml", "width = 64", "width = 65")
    with pytest.raises(DataError, match="64x48 but run.toml says 65x48"):
        read_run(folder)


def test_tum_readable_by_evo(tmp_path):
    from evo.tools import file_interface

    run, _ = make_run(n_frames=20)
    write_tum(tmp_path / "t.tum", run.truth_times, run.truth_poses)
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "t.tum"))
    np.testing.assert_allclose(traj.timestamps, run.truth_times, atol=1e-9)
    np.testing.assert_allclose(np.stack(traj.poses_se3), run.truth_poses, atol=1e-9)
    # and evo's writer produces a file we read back
    file_interface.write_tum_trajectory_file(str(tmp_path / "evo.tum"), traj)
    t, P = read_tum(tmp_path / "evo.tum")
    np.testing.assert_allclose(P, run.truth_poses, atol=1e-6)


def test_pose_interpolation(run_dir):
    folder, run, _ = run_dir
    r = read_run(folder)
    mid = r.pose_at(0.5 * (r.truth_times[1] + r.truth_times[2]), which="truth")
    np.testing.assert_allclose(mid[:3, 3], 0.5 * (run.truth_poses[1, :3, 3] + run.truth_poses[2, :3, 3]))
    inc = r.odometry_increments()
    np.testing.assert_allclose(r.odometry_poses[0] @ inc[0], r.odometry_poses[1], atol=1e-12)
