"""Sliding-window pose graph: odometry + localisation factors, window, late constraints, failure rule."""
import gtsam
import numpy as np
import pytest

from scenesig.localiser.failure import FAILURE_DISTANCE_M, is_failure
from scenesig.localiser.posegraph import PoseGraph
from scenesig.localiser.solver import pose_exp, pose_log
from scenesig.surveys.geometry import invert, make_pose, rot_z

DT = 0.05
ODO_SIG = np.array([1e-3, 1e-3, 2e-3, 0.02, 0.01, 0.01])
ODO_COV = np.diag(ODO_SIG ** 2)
LOC_SIG = np.array([0.005, 0.005, 0.01, 0.3, 0.3, 0.3])
LOC_COV = np.diag(LOC_SIG ** 2)
START_COV = np.diag([1e-4] * 3 + [1e-2] * 3)


def trajectory(n, speed=10.0, yaw_rate=0.1):
    """Truth at 20 Hz: a constant-twist arc (so tangent-space interpolation is exact)."""
    step = make_pose(rot_z(yaw_rate * DT), [speed * DT, 0, 0])
    T = [make_pose(rot_z(0.3), [5.0, -2.0, 1.0])]
    for _ in range(n - 1):
        T.append(T[-1] @ step)
    return np.array(T)


def noisy_odometry(truth, rng, bias=(0, 0, 0.0005, 0.01, 0, 0)):
    incs = invert(truth[:-1]) @ truth[1:]
    return np.array([inc @ pose_exp(rng.normal(0, 1, 6) * ODO_SIG + np.asarray(bias)) for inc in incs])


def test_recovers_known_pose_from_noisy_odometry_and_localisations():
    rng = np.random.default_rng(0)
    truth = trajectory(300)
    odo = noisy_odometry(truth, rng)
    g = PoseGraph(window_seconds=5.0)
    g.reset(0.0, truth[0], START_COV)
    dead = truth[0].copy()
    err, err_loc, err_yaw = [], [], []
    for k in range(1, len(truth)):
        g.add_odometry(k * DT, odo[k - 1], ODO_COV)
        dead = dead @ odo[k - 1]
        if k % 4 == 0:
            z = truth[k] @ pose_exp(rng.normal(0, 1, 6) * LOC_SIG)
            g.add_localisation(k * DT, z, cov=LOC_COV)
            if k > 150:
                err_loc.append(np.linalg.norm(z[:3, 3] - truth[k][:3, 3]))
        if k > 150:
            err.append(np.linalg.norm(g.estimate()[:3, 3] - truth[k][:3, 3]))
            err_yaw.append(np.degrees(abs(pose_log(invert(truth[k]) @ g.estimate())[2])))
    err_dead = np.linalg.norm(dead[:3, 3] - truth[-1][:3, 3])
    assert err_dead > 5.0                           # odometry alone is far off ...
    assert np.mean(err) < 0.7 * np.mean(err_loc)    # ... the graph beats its own localisations
    assert np.max(err) < 0.8 and np.mean(err_yaw) < 0.6


def test_matches_full_batch_optimisation():
    # The smoother (keyframes, composed odometry, marginalisation) against a batch LM over every
    # 20 Hz pose with the same factors: the latest pose must agree.
    rng = np.random.default_rng(1)
    truth = trajectory(120)
    odo = noisy_odometry(truth, rng)
    locs = {k: truth[k] @ pose_exp(rng.normal(0, 1, 6) * LOC_SIG) for k in range(6, 120, 6)}
    g = PoseGraph(window_seconds=3.0, keyframe_interval_s=0.25, config={"extra_iterations": 2})
    g.reset(0.0, truth[0], START_COV)
    X = gtsam.symbol_shorthand.X
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(truth[0]), gtsam.noiseModel.Gaussian.Covariance(START_COV)))
    values.insert(X(0), gtsam.Pose3(truth[0]))
    cur = truth[0]
    huber = gtsam.noiseModel.mEstimator.Huber.Create(g.config["huber_k"])
    for k in range(1, len(truth)):
        g.add_odometry(k * DT, odo[k - 1], ODO_COV)
        cur = cur @ odo[k - 1]
        graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), gtsam.Pose3(odo[k - 1]),
                                           gtsam.noiseModel.Gaussian.Covariance(ODO_COV)))
        values.insert(X(k), gtsam.Pose3(cur))
        if k in locs:
            g.add_localisation(k * DT, locs[k], cov=LOC_COV)
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(locs[k]), gtsam.noiseModel.Robust.Create(
                huber, gtsam.noiseModel.Gaussian.Covariance(LOC_COV))))
    batch = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize().atPose3(X(len(truth) - 1)).matrix()
    d = pose_log(invert(batch) @ g.estimate())
    assert np.linalg.norm(d[3:]) < 0.02 and np.degrees(np.linalg.norm(d[:3])) < 0.02
    # ... and far from the dead-reckoned guess, so the agreement is not trivial.
    assert np.linalg.norm(cur[:3, 3] - batch[:3, 3]) > 0.5


def test_perfect_odometry_is_integrated_exactly_between_keyframes():
    truth = trajectory(60)
    g = PoseGraph(window_seconds=10.0)
    g.reset(0.0, truth[0], START_COV)
    for k in range(1, len(truth)):
        g.add_odometry(k * DT, invert(truth[k - 1]) @ truth[k], ODO_COV)
        assert g.estimate() == pytest.approx(truth[k], abs=1e-9)
    # Between samples: constant-twist motion, so interpolation is exact too.
    t = 37.5 * DT
    expected = truth[37] @ pose_exp(0.5 * pose_log(invert(truth[37]) @ truth[38]))
    assert g.estimate(t) == pytest.approx(expected, abs=1e-9)
    assert g.estimate(20 * DT) == pytest.approx(truth[20], abs=1e-9)


def test_localisation_between_odometry_samples_and_late_localisation():
    rng = np.random.default_rng(2)
    truth = trajectory(200)
    odo = noisy_odometry(truth, rng, bias=(0, 0, 0.004, 0.03, 0.02, 0))
    tight = np.diag([1e-6] * 3 + [1e-4] * 3)
    # The biased odometry is far outside its covariance, so Huber would (rightly) distrust the
    # constraints; this test is about carrying them to the right keyframe, hence plain least squares.
    g = PoseGraph(window_seconds=5.0, huber_k=1e6)
    g.reset(0.0, truth[0], START_COV)
    for k in range(1, 61):
        g.add_odometry(k * DT, odo[k - 1], ODO_COV)
    # Keyframes fall every 5 samples (0.25 s), the latest at sample 60.  A localisation half-way
    # between samples 57 and 58 arrives late: it is carried to a keyframe along the odometry.
    t_late = 57.5 * DT
    T_late = truth[57] @ pose_exp(0.5 * pose_log(invert(truth[57]) @ truth[58]))
    before = np.linalg.norm(g.estimate(t_late)[:3, 3] - T_late[:3, 3])
    assert g.add_localisation(t_late, T_late, cov=tight)
    after = np.linalg.norm(g.estimate(t_late)[:3, 3] - T_late[:3, 3])
    assert before > 3.0 and after < 0.15      # the rest is the odometry bias over 2.5 samples
    # A localisation inside the running odometry (after the latest keyframe, before the latest
    # sample) splits it; the estimate there lands on the constraint.
    for k in range(61, 64):
        g.add_odometry(k * DT, odo[k - 1], ODO_COV)
    t_mid = 62.25 * DT
    T_mid = truth[62] @ pose_exp(0.25 * pose_log(invert(truth[62]) @ truth[63]))
    assert g.add_localisation(t_mid, T_mid, cov=tight)
    assert np.linalg.norm(g.estimate(t_mid)[:3, 3] - T_mid[:3, 3]) < 0.01
    assert np.linalg.norm(g.estimate()[:3, 3] - truth[63][:3, 3]) < 0.05
    # Too old for the window: dropped.
    for k in range(64, 200):
        g.add_odometry(k * DT, odo[k - 1], ODO_COV)
    assert not g.add_localisation(0.1, truth[2], cov=tight)


def test_huber_limits_an_outlier_localisation():
    truth = trajectory(41, yaw_rate=0.0)
    moved = {}
    for k_h in (3.0, 1e6):
        g = PoseGraph(huber_k=k_h)
        g.reset(0.0, truth[0], START_COV)
        for k in range(1, 41):
            g.add_odometry(k * DT, invert(truth[k - 1]) @ truth[k], ODO_COV)
        g.add_localisation(40 * DT, truth[40] @ make_pose(t=[0, 10.0, 0]), cov=LOC_COV)   # 10 m off
        moved[k_h] = np.linalg.norm(g.estimate()[:3, 3] - truth[40][:3, 3])
    assert moved[1e6] > 2.0 and moved[3.0] < 0.3 * moved[1e6]


def test_window_marginalises_old_keyframes():
    truth = trajectory(200)
    g = PoseGraph(window_seconds=2.0, keyframe_interval_s=0.25)
    g.reset(0.0, truth[0], START_COV)
    for k in range(1, 200):
        g.add_odometry(k * DT, invert(truth[k - 1]) @ truth[k], ODO_COV)
    times, poses = g.keyframes()
    assert times[-1] == pytest.approx(199 * DT - 4 * DT)       # keyframes every 5 samples
    assert times[-1] - times[0] <= 2.0 + 1e-9 and len(times) >= 8
    assert poses[-1] == pytest.approx(truth[195], abs=1e-6)
    with pytest.raises(ValueError, match="before the window"):
        g.estimate(1.0)


def test_singular_information_corrects_only_what_it_sees():
    # A localisation that only knows the lateral offset and the heading (far-field signatures):
    # it fixes those and leaves the along-track estimate to odometry.
    truth = trajectory(41, yaw_rate=0.0)
    g = PoseGraph(window_seconds=10.0)
    wrong = truth[0] @ make_pose(rot_z(0.02), [3.0, 1.5, 0.0])      # 3 m ahead, 1.5 m left, 1.1° off
    g.reset(0.0, wrong, np.diag([1e-2] * 3 + [25.0] * 3))
    for k in range(1, 41):
        g.add_odometry(k * DT, invert(truth[k - 1]) @ truth[k], ODO_COV)
    info = np.zeros((6, 6))
    info[2, 2] = 1 / 0.002 ** 2          # yaw
    info[4, 4] = 1 / 0.05 ** 2           # lateral (vehicle y)
    g.add_localisation(40 * DT, truth[40], information=info)
    err = invert(truth[40]) @ g.estimate()
    assert abs(err[1, 3]) < 0.1                                   # lateral fixed
    assert abs(np.degrees(np.arctan2(err[1, 0], err[0, 0]))) < 0.1  # heading fixed
    assert err[0, 3] > 2.0                                        # along-track untouched


def test_covariance_grows_blind_and_shrinks_when_localised():
    truth = trajectory(40)
    g = PoseGraph()
    g.reset(0.0, truth[0], START_COV)
    sizes = []
    for k in range(1, 40):
        g.add_odometry(k * DT, invert(truth[k - 1]) @ truth[k], ODO_COV)
        sizes.append(np.trace(g.covariance()[3:, 3:]))
    assert np.all(np.diff(sizes) > 0)
    g.add_localisation(39 * DT, truth[39], cov=LOC_COV)
    assert np.trace(g.covariance()[3:, 3:]) < 0.5 * sizes[-1]


def test_reset_restarts_the_graph():
    truth = trajectory(60, speed=10.0, yaw_rate=0.0)   # 0.5 m per sample
    g = PoseGraph()
    g.reset(0.0, truth[0], START_COV)
    for k in range(1, 42):
        g.add_odometry(k * DT, invert(truth[k - 1]) @ truth[k], ODO_COV)
    g.reset(41 * DT, truth[41], START_COV)
    assert g.estimate() == pytest.approx(truth[41])
    assert np.trace(g.covariance()) == pytest.approx(np.trace(START_COV))


def test_failure_rule_once():
    # McManus et al. 2015, §4.3: more than 20 m blind; summed increments at exactly 20 m are not a failure
    assert FAILURE_DISTANCE_M == 20.0
    assert not is_failure(sum([1.0] * 20)) and not is_failure(sum([0.1] * 200))
    assert is_failure(20.01) and is_failure(6.0, failure_distance_m=5.0)
    with pytest.raises(ValueError, match="failure_distance_m"):
        is_failure(1.0, failure_distance_m=0.0)
    # the pose graph has no failure rule of its own (nothing to overwrite a user's setting with)
    with pytest.raises(ValueError, match="failure_distance_m"):
        PoseGraph(config={"failure_distance_m": 5.0})


def test_bad_input():
    g = PoseGraph()
    with pytest.raises(RuntimeError, match="reset"):
        g.add_odometry(0.1, np.eye(4), ODO_COV)
    g.reset(0.0, np.eye(4), START_COV)
    with pytest.raises(ValueError, match="not after"):
        g.add_odometry(0.0, np.eye(4), ODO_COV)
    with pytest.raises(ValueError, match="positive definite"):
        g.add_odometry(0.1, np.eye(4), -ODO_COV)
    with pytest.raises(ValueError, match="rigid"):
        g.add_odometry(0.1, np.diag([2.0, 1, 1, 1]), ODO_COV)
    with pytest.raises(ValueError, match="exactly one"):
        g.add_localisation(0.0, np.eye(4))
    with pytest.raises(ValueError, match="semi-definite"):
        g.add_localisation(0.0, np.eye(4), information=-np.eye(6))
    with pytest.raises(ValueError, match="unknown pose-graph option"):
        PoseGraph(config={"window": 3})


def test_update_is_fast():
    # ~0.2 ms per smoother update measured; fail only if an order of magnitude slower.
    rng = np.random.default_rng(3)
    truth = trajectory(400)
    odo = noisy_odometry(truth, rng)
    g = PoseGraph(window_seconds=5.0)
    g.reset(0.0, truth[0], START_COV)
    for k in range(1, len(truth)):
        g.add_odometry(k * DT, odo[k - 1], ODO_COV)
        if k % 4 == 0:
            g.add_localisation(k * DT, truth[k], cov=LOC_COV)
    assert g.n_updates > 150 and g.ms_per_update < 5.0
