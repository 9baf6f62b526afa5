"""SE(2) snapping onto the local plane of the two nearest keyframes (§3.3.3, Fig. 7)."""
import numpy as np
import pytest

from scenesig.localiser.se2 import PlaneSnapper, local_plane, snap_to_keyframes, snap_to_plane
from scenesig.surveys.geometry import exp_so3, make_pose, rot_x, rot_y, rot_z, yaw_of


def tilted_road(n=6, spacing=10.0, grade=0.08, bank=0.05, yaw=0.3):
    """Keyframes on one tilted plane: a straight road climbing at ``grade`` with a ``bank`` roll."""
    R_road = rot_z(yaw) @ rot_y(-np.arctan(grade)) @ rot_x(bank)   # x along the road, z its normal
    origin = np.array([100.0, -50.0, 7.0])
    return np.stack([make_pose(R_road, origin + R_road[:, 0] * spacing * k) for k in range(n)]), R_road, origin


def test_snap_is_exact_on_tilted_plane():
    kfs, R_road, origin = tilted_road()
    normal = R_road[:, 2]
    rng = np.random.default_rng(1)
    snapper = PlaneSnapper(kfs)
    for _ in range(20):
        # A pose near the road, off the plane by up to a metre, with some roll and pitch.
        p = origin + R_road @ np.array([rng.uniform(0, 50), rng.uniform(-3, 3), rng.uniform(-1, 1)])
        R = R_road @ exp_so3(rng.normal(0, 0.1, 3))
        T = make_pose(R, p)
        S = snapper.snap(T)
        assert S[:3, 2] == pytest.approx(normal, abs=1e-9)                  # z axis = plane normal
        assert (S[:3, 3] - origin) @ normal == pytest.approx(0.0, abs=1e-9)  # on the plane
        # Position moved only along the normal.
        d = S[:3, 3] - p
        assert np.linalg.norm(d - (d @ normal) * normal) < 1e-9
        # Heading within the plane kept: new x is the old x projected into the plane.
        x_in = R[:, 0] - (R[:, 0] @ normal) * normal
        assert S[:3, 0] == pytest.approx(x_in / np.linalg.norm(x_in), abs=1e-9)
        assert np.allclose(S[:3, :3] @ S[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(S[:3, :3]) == pytest.approx(1.0, abs=1e-12)
        # Idempotent.
        assert np.allclose(snapper.snap(S), S, atol=1e-12)


def test_plane_passes_through_both_keyframes_and_uses_lateral_axis():
    kfs, R_road, _ = tilted_road()
    point, n = local_plane(kfs[1], kfs[2])
    for k in (1, 2):
        assert (kfs[k][:3, 3] - point) @ n == pytest.approx(0.0, abs=1e-9)
    assert n @ kfs[1][:3, 1] == pytest.approx(0.0, abs=1e-9)   # contains the lateral axis (bank)
    assert n[2] > 0                                             # points up


def test_plane_uses_positions_not_keyframe_pitch():
    # Keyframes pitched differently from the baseline between them: the plane follows the positions.
    a = make_pose(rot_y(0.2), [0, 0, 0])
    b = make_pose(rot_y(0.2), [10, 0, 1.0])
    point, n = local_plane(a, b)
    assert n @ np.array([10, 0, 1.0]) == pytest.approx(0.0, abs=1e-12)
    assert n == pytest.approx(np.array([-1.0, 0, 10.0]) / np.sqrt(101), abs=1e-12)


def test_degenerate_baseline_falls_back_to_average_normal():
    a = make_pose(rot_x(0.1), [0, 0, 0])
    b = make_pose(rot_x(0.1), [0, 0, 0])       # same position
    point, n = local_plane(a, b)
    assert n == pytest.approx(rot_x(0.1)[:, 2], abs=1e-12)


def test_flat_road_keeps_yaw_and_zeroes_z_roll_pitch():
    kfs = np.stack([make_pose(np.eye(3), [10.0 * k, 0, 0]) for k in range(3)])
    T = make_pose(rot_z(0.4) @ rot_y(0.05) @ rot_x(-0.03), [12.0, 1.0, 0.7])
    S = snap_to_keyframes(T, kfs)
    assert S[2, 3] == pytest.approx(0.0, abs=1e-12)
    assert S[:2, 3] == pytest.approx(T[:2, 3], abs=1e-12)
    assert yaw_of(S) == pytest.approx(yaw_of(T), abs=1e-12)
    assert S[:3, 2] == pytest.approx([0, 0, 1], abs=1e-12)


def test_nearest_two_keyframes_are_used():
    # Two road sections at different heights: the snap must use the section it is on.
    low = [make_pose(np.eye(3), [10.0 * k, 0, 0]) for k in range(3)]
    high = [make_pose(np.eye(3), [10.0 * k, 100.0, 5.0]) for k in range(3)]
    snapper = PlaneSnapper(np.stack(low + high))
    assert snapper.snap(make_pose(np.eye(3), [5, 99, 6.0]))[2, 3] == pytest.approx(5.0)
    assert snapper.snap(make_pose(np.eye(3), [5, 1, -0.5]))[2, 3] == pytest.approx(0.0)
    assert set(snapper.nearest_two([4, 0, 0])) == {0, 1}


def test_bad_input():
    with pytest.raises(ValueError, match="at least 2"):
        PlaneSnapper(np.eye(4)[None])
    with pytest.raises(ValueError, match="4x4"):
        snap_to_plane(np.eye(3), [0, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="normalise"):
        snap_to_plane(np.eye(4), [0, 0, 0], [0, 0, 0])
