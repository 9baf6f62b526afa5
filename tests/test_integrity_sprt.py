"""The integrity monitor's sequential test (Wald's SPRT in probation, Page's CUSUM while tracking) on
synthetic Bernoulli streams, the firing-rate file beside a map, and the integrity bench's plumbing."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scenesig.localiser.integrity import FrameStats, IntegrityMonitor

OWN, OTHER = 0.6, 0.1          # a place's firing rates: on its own place, elsewhere
SEARCHED = 40                  # signatures searched per frame
#: independent firings (dispersion 1), uncensored: the setting in which Wald's bounds hold as stated
DESIGN = {"sprt_alpha": 0.01, "sprt_beta": 0.01, "sprt_other_factor": 1.0, "sprt_own_fraction": 0.5,
          "sprt_dispersion": 1.0, "cusum_h": 8.0, "sprt_probation_frames": 6, "sprt_probation_places": 2,
          "sprt_lookalike_places": 0}


def _p1():
    return OTHER + DESIGN["sprt_own_fraction"] * (OWN - OTHER)


def _chance(monitor) -> int:
    """The signatures fired, of ``SEARCHED``, whose frame evidence is nearest 0 at the test's place rates: the
    odds of neither hypothesis (a look-alike's places after the ones that fool it)."""
    return min(range(SEARCHED + 1), key=lambda k: abs(monitor._llr_of(3, k, SEARCHED)))


def _frame(rng, t, place, rate):
    k = int(rng.binomial(SEARCHED, rate))
    # residual and innovation unknown (NaN): only the sequential test speaks
    return FrameStats(t, place, k, k, SEARCHED, True, np.nan, 1.0, np.nan, np.nan)


def _probation(rng, rate, rates):
    m = IntegrityMonitor(DESIGN, firing=rates)
    m.begin_probation(0.0)
    for i in range(200):
        v = m.assess(_frame(rng, 0.2 * i, 3 + i, rate))      # one frame per place: independent draws
        if v in ("accept", "alert"):
            return v, i + 1
    return "undecided", 200


def test_sprt_error_rates_are_within_the_design():
    rng = np.random.default_rng(0)
    rates = {p: (OWN, OTHER) for p in range(200)}
    n = 1500
    right = [_probation(rng, _p1(), rates) for _ in range(n)]
    wrong = [_probation(rng, OTHER, rates) for _ in range(n)]
    false_alarm = np.mean([v != "accept" for v, _ in right])
    missed = np.mean([v == "accept" for v, _ in wrong])
    # Wald: the realised rates are at most alpha / (1 - beta) and beta / (1 - alpha) (plus sampling noise:
    # 3 binomial standard deviations at n = 1500)
    a, b = DESIGN["sprt_alpha"], DESIGN["sprt_beta"]
    assert missed <= a / (1 - b) + 3 * np.sqrt(a / n)
    assert false_alarm <= b / (1 - a) + 3 * np.sqrt(b / n)
    # and it decides: right fixes are accepted after the minimum probation, wrong ones refused quickly
    assert np.median([k for v, k in right]) <= 8 and np.median([k for v, k in wrong]) <= 4


def test_sprt_at_the_midpoint_rate_is_undecided_and_alerts():
    rng = np.random.default_rng(1)
    rates = {p: (OWN, OTHER) for p in range(200)}
    out = [_probation(rng, 0.5 * (OTHER + _p1()), rates)[0] for _ in range(200)]
    assert set(out) <= {"accept", "alert"}     # sprt_probation_max_places ends every probation


def test_cusum_rarely_alerts_on_the_right_map_and_quickly_on_another():
    rng = np.random.default_rng(2)
    rates = {p: (OWN, OTHER) for p in range(1000)}
    runs = 200
    alerted = 0
    for _ in range(runs):
        m = IntegrityMonitor(DESIGN, firing=rates)
        for i in range(150):
            m.assess(_frame(rng, 0.2 * i, i, _p1()))
        alerted += bool(m.alerts)
    # ARL under H1 of Page's test is at least e^h places: 150 places alert with probability <= 150 e^-h
    assert alerted / runs <= 150 * np.exp(-DESIGN["cusum_h"]) + 3 * np.sqrt(0.05 / runs)
    m = IntegrityMonitor(DESIGN, firing=rates)
    for i in range(20):
        m.assess(_frame(rng, 0.2 * i, 0, _p1()))
    assert not m.alerts
    verdicts = [m.assess(_frame(rng, 4 + 0.2 * i, 100 + i, OTHER)) for i in range(10)]
    assert "alert" in verdicts[:6] and "sequential test" in m.alerts[0].reason


def test_a_place_counts_once_however_long_the_vehicle_stands_there():
    """A look-alike seen for seconds at a crossing is one place's evidence, not one per frame."""
    rng = np.random.default_rng(4)
    rates = {p: (OWN, OTHER) for p in range(10)}
    m = IntegrityMonitor(DESIGN, firing=rates)
    m.begin_probation(0.0)
    # a look-alike: firing at H1's rate, at one place for 40 frames -- not accepted (one place)
    assert {m.assess(_frame(rng, 0.2 * i, 3, _p1())) for i in range(40)} == {"tentative"}
    one_place = m._llr
    # the same evidence once: the LLR of the place's mean firing (about 9 here), not 40 times it (~360)
    single = m._llr_of(3, _p1() * SEARCHED, SEARCHED)
    assert abs(one_place - single) < 0.5 * single
    # the next place fires at another place's rate: the test ends with an alert
    assert "alert" in [m.assess(_frame(rng, 8 + 0.2 * i, 4 + i, OTHER)) for i in range(6)]


def test_places_are_counted_in_odometry_not_in_estimated_places():
    """A wrong map's estimate can cross place boundaries while the vehicle creeps: with the odometry recorded,
    neither the evidence nor the probation's places count a new place until a place spacing has been driven."""
    rng = np.random.default_rng(5)
    rates = {p: (OWN, OTHER) for p in range(100)}
    unit = IntegrityMonitor(DESIGN, firing=rates).config["sprt_unit_m"]

    def frame(i, place, odometry_m):
        k = int(rng.binomial(SEARCHED, _p1()))
        return FrameStats(0.2 * i, place, k, k, SEARCHED, True, np.nan, 1.0, np.nan, np.nan, odometry_m)

    # creeping 0.05 m a frame while the estimate walks a place every frame: 40 frames, 2 m, one unit
    m = IntegrityMonitor(DESIGN, firing=rates)
    m.begin_probation(0.0)
    assert {m.assess(frame(i, 3 + i, 100.0 + 0.05 * i)) for i in range(40)} == {"tentative"}
    assert m._llr < 2 * m._llr_of(3, _p1() * SEARCHED, SEARCHED)
    # the same firing while driving a place spacing every 5 frames: accepted once a spacing has been driven
    m = IntegrityMonitor(DESIGN, firing=rates)
    m.begin_probation(0.0)
    verdicts = [m.assess(frame(i, 3, 100.0 + unit / 5 * i)) for i in range(40)]
    first = verdicts.index("accept")
    assert set(verdicts[:first]) == {"tentative"} and first >= 5
    # without odometry (older recordings) the estimated place keys both, as before
    m = IntegrityMonitor(DESIGN, firing=rates)
    m.begin_probation(0.0)
    assert "accept" in [m.assess(_frame(rng, 0.2 * i, 3 + i, _p1())) for i in range(40)]


def test_a_look_alike_that_fails_at_the_next_place_is_not_accepted_there():
    """A look-alike fires like the map for a few places and fails at the next.  With
    ``sprt_confirming_place`` the fix is accepted only at a place whose own evidence is for the map: the
    look-alike, whose minimum probation ends on the failing place, is not accepted, and ends with an alert;
    the same places followed by a confirming one are accepted there."""
    rates = {p: (OWN, OTHER) for p in range(20)}
    cfg = {**DESIGN, "sprt_probation_places": 4, "sprt_confirming_place": True}
    strong, silent = int(OWN * SEARCHED), 0

    def drive(firing_per_place):
        m = IntegrityMonitor(cfg, firing=rates)
        m.begin_probation(0.0)
        out = []
        for i, k in enumerate(firing_per_place):        # 5 frames per place spacing of odometry
            f = FrameStats(0.2 * i, 3 + i // 5, k, k, SEARCHED, True, np.nan, 1.0, np.nan, np.nan, 2.0 * i)
            out.append(m.assess(f))
            if out[-1] in ("accept", "alert"):
                break
        return out

    look_alike = drive([strong] * 15 + [silent] * 40)
    assert "accept" not in look_alike and look_alike[-1] == "alert"
    # the same look-alike without the rule is accepted on the failing place's first frame
    cfg["sprt_confirming_place"] = False
    assert drive([strong] * 15 + [silent] * 30)[-1] == "accept"
    cfg["sprt_confirming_place"] = True
    right = drive([strong] * 40)
    assert right[-1] == "accept" and len(right) == 16      # the first frame of the fourth place


def test_the_censored_test_does_not_accept_on_a_few_look_alike_places():
    """Huber's censored SPRT: with ``sprt_lookalike_places`` L, no place counts for more than log((1-β)/α) /
    (L + 1).  L places that fire like the map's and the rest at chance (the odds of neither hypothesis) do not
    reach the acceptance bound, however strongly the L fire; uncensored, two strong places outweigh four at
    chance and the fix is accepted.  A right map, every place firing, is still accepted after the minimum
    probation; and a bad place (nothing fires) costs a right map at most one cap."""
    rates = {p: (OWN, OTHER) for p in range(30)}
    strong = SEARCHED                                 # every signature fires: far beyond H1's rate
    m0 = IntegrityMonitor({**DESIGN, "sprt_lookalike_places": 0}, firing=rates)
    chance = _chance(m0)
    assert abs(m0._llr_of(3, chance, SEARCHED)) < 0.5 * m0._llr_of(3, 1, 1)

    def drive(cfg, firing_per_place, frames_per_place=5):
        # the confirming place is another rule (the test above): here the sum alone decides
        m = IntegrityMonitor({**DESIGN, "sprt_probation_places": 6, "sprt_confirming_place": False, **cfg},
                             firing=rates)
        m.begin_probation(0.0)
        out = []
        for i, k in enumerate(np.repeat(firing_per_place, frames_per_place)):
            f = FrameStats(0.2 * i, 3 + i // frames_per_place, int(k), int(k), SEARCHED, True, np.nan, 1.0,
                           np.nan, np.nan, 2.0 * i)
            out.append(m.assess(f))
            if out[-1] in ("accept", "alert"):
                break
        return m, out

    look_alike = [strong, strong] + [chance] * 4
    _, uncensored = drive({"sprt_lookalike_places": 0}, look_alike)
    assert uncensored[-1] == "accept"
    for lookalikes in (2, 3):
        m, out = drive({"sprt_lookalike_places": lookalikes}, [strong] * lookalikes
                       + [chance] * (6 - lookalikes))
        assert m.unit_cap == pytest.approx(m.upper / (lookalikes + 1))
        assert "accept" not in out and m._llr < m.upper
    m, out = drive({"sprt_lookalike_places": 2}, [strong] * 8)
    assert out[-1] == "accept" and len(out) == 26          # the first frame of the sixth place's spacing
    # a right map with one place at which nothing fires: censored, it loses one cap and is still accepted
    m, out = drive({"sprt_lookalike_places": 2}, [strong] * 2 + [0] + [strong] * 8)
    assert out[-1] == "accept"
    with pytest.raises(ValueError, match="sprt_lookalike_places"):
        IntegrityMonitor({"sprt_lookalike_places": -1}, firing=rates)


def test_the_probation_is_limited_in_places_not_frames():
    """A slow vehicle gives many frames per place: the censored test, which needs L + 1 places or more, must
    not run out of frames.  A right map driven at 0.3 m a frame is accepted after the minimum probation's six
    places (50 m, 170 frames); a probation at chance ends undecided, with an alert, at
    ``sprt_probation_max_places`` places however many frames that took."""
    rng = np.random.default_rng(7)
    rates = {p: (OWN, OTHER) for p in range(100)}
    cfg = {**DESIGN, "sprt_lookalike_places": 2, "sprt_probation_places": 6, "sprt_confirming_place": True,
           "sprt_dispersion": 4.0}
    probe = IntegrityMonitor(cfg, firing=rates)
    chance = _chance(probe)
    assert 12 * abs(probe._llr_of(3, chance, SEARCHED)) < min(probe.upper, -probe.lower)

    def drive(rate, step_m, frames):
        m = IntegrityMonitor(cfg, firing=rates)
        m.begin_probation(0.0)
        for i in range(frames):
            k = int(rng.binomial(SEARCHED, rate)) if rate is not None else chance
            v = m.assess(FrameStats(0.2 * i, int(step_m * i // 10), k, k, SEARCHED, True, np.nan, 1.0, np.nan,
                                    np.nan, step_m * i))
            if v in ("accept", "alert"):
                return m, v, i
        return m, "tentative", frames

    m, v, i = drive(OWN, 0.3, 400)
    assert v == "accept" and 50 / 0.3 <= i < 60 / 0.3
    m, v, i = drive(None, 0.3, 1000)
    assert v == "alert" and "undecided after 12 places" in m.alerts[0].reason
    assert i == int(np.ceil(110 / 0.3 - 1e-9))          # the first frame of the twelfth place


def test_a_frame_without_a_pose_counts_its_inliers_not_its_detections():
    """Detections the solver's geometry rejected are no evidence for the map: a look-alike's windows fill with
    chance responses (up to every signature searched) that no pose explains.  The rates in firing.json count
    the solver's inliers on every frame; the monitor counts the same."""
    rates = {p: (OWN, OTHER) for p in range(10)}
    m = IntegrityMonitor(DESIGN, firing=rates)
    # every signature searched responded, 2 survived the solver's gates, and it rejected the pose
    rejected = FrameStats(0.0, 3, SEARCHED, 2, SEARCHED, False, np.nan, 1.0, np.nan, np.nan)
    assert m.frame_llr(rejected) < 0
    assert m.frame_llr(rejected) == pytest.approx(
        m.frame_llr(FrameStats(0.0, 3, 2, 2, SEARCHED, True, np.nan, 1.0, np.nan, np.nan)))
    # a probation fed such frames at one place after another is refused, never accepted
    m.begin_probation(0.0)
    verdicts = [m.assess(FrameStats(0.2 * i, 3 + i, SEARCHED, 2, SEARCHED, False, np.nan, 1.0, np.nan, np.nan))
                for i in range(8)]
    assert "accept" not in verdicts and "alert" in verdicts


def test_without_firing_rates_the_thresholds_decide():
    m = IntegrityMonitor(DESIGN, firing=None)
    assert m.rates is None and m.frame_llr(FrameStats(0, 1, 5, 5, 40, True, 1, 4, 1, 0.1)) == 0.0
    m = IntegrityMonitor({**DESIGN, "sprt": False}, firing={1: (OWN, OTHER)})
    assert m.rates is None
    with pytest.raises(ValueError, match="sprt_alpha"):
        IntegrityMonitor({"sprt_alpha": 0.7}, firing={1: (OWN, OTHER)})


def test_firing_file_belongs_to_one_map_state(tmp_path, caplog):
    from scenesig.localiser import firing

    class Store:
        root = tmp_path
        map_id = "a"
        generation = 0

    assert firing.load(Store) is None                                    # an old map: none
    doc = {"version": firing.VERSION, "map_id": "a", "generation": 0, "settings": {},
           "places": {"2": {"own": 0.5, "other": 0.1}}}
    (tmp_path / firing.FILE).write_text(json.dumps(doc))
    assert firing.load(Store) == {2: (0.5, 0.1)}
    Store.generation = 1                                                  # updated since: stale
    assert firing.load(Store) is None and "another map state" in caplog.text
    (tmp_path / firing.FILE).write_text("{")
    from scenesig.surveys.errors import DataError

    with pytest.raises(DataError, match="firing"):
        firing.load(Store)


def test_bench_seeds_and_summary():
    from scenesig.benchmarks.integrity import parse_seeds, summarise

    assert parse_seeds("3-5,9") == [3, 4, 5, 9]
    for bad in ("5", "x-3", "5-3"):
        with pytest.raises(ValueError):
            parse_seeds(bad)
    runs = [{"kind": "wrong", "run": "drive1", "localisations": 0, "integrity_alerts": 2, "false_fixes": 0,
             "failures": 0, "bound_coverage_95": None, "lateral_bound_95_m": None},
            {"kind": "wrong", "run": "drive3", "localisations": 4, "integrity_alerts": 1, "false_fixes": 4,
             "failures": 0, "bound_coverage_95": None, "lateral_bound_95_m": None},
            {"kind": "right", "localisations": 90, "integrity_alerts": 0, "false_fixes": 0, "failures": 0,
             "bound_coverage_95": 0.95, "lateral_bound_95_m": 0.5},
            {"kind": "right", "localisations": 80, "integrity_alerts": 1, "false_fixes": 0, "failures": 0,
             "bound_coverage_95": 0.85, "lateral_bound_95_m": 0.7}]
    s = summarise([{"seed": 1, "runs": runs}])
    assert s["wrong_runs_zero_accepted_rate"] == 0.5 and s["wrong_run_max_accepted"] == 4
    assert s["right_runs_with_alert_rate"] == 0.5 and s["right_runs_coverage_ok_rate"] == 0.5
    # the second partner's run is in the totals, not in the first partner's figures
    assert s["wrong_first_partner"] == {"wrong_runs": 1, "wrong_runs_zero_accepted_rate": 1.0,
                                        "wrong_run_max_accepted": 0}
    assert s["wrong_runs_accepted"] == ["1/drive3: 4"]


def test_bench_partner_worlds_and_their_run_names():
    """Each map meets the runs of the next ``count`` worlds of the list (never its own); the first partner's
    copies keep the names a one-partner cache holds."""
    from scenesig.benchmarks.integrity import partner_worlds, wrong_alias

    assert partner_worlds([1, 2, 3], 1) == {1: [2], 2: [3], 3: [1]}
    assert partner_worlds([1, 2, 3], 2) == {1: [2, 3], 2: [3, 1], 3: [1, 2]}
    assert partner_worlds([1, 2], 5) == {1: [2], 2: [1]}
    assert [wrong_alias(j, i) for j in range(2) for i in range(2)] == ["drive1", "drive2", "drive3", "drive4"]


def test_bench_cache_keys_follow_the_defaults_the_localisations_depend_on(monkeypatch):
    """A cached localisation is not reused once a default it depends on changes: the localiser block's (both
    modes; its innovation term an evaluation only), the monitor's (an evaluation only)."""
    from scenesig.benchmarks import integrity as bench
    from scenesig.localiser import integrity, pipeline

    before = {mode: bench._defaults_key(mode) for mode in ("calibrate", "evaluate")}
    monkeypatch.setitem(pipeline.default_config, "view_baseline_m", 0.5)
    assert all(bench._defaults_key(mode) != key for mode, key in before.items())
    monkeypatch.undo()
    monkeypatch.setitem(integrity.default_config, "cusum_h", integrity.default_config["cusum_h"] + 1)
    assert bench._defaults_key("calibrate") == before["calibrate"]
    assert bench._defaults_key("evaluate") != before["evaluate"]
    monkeypatch.undo()
    # the bound model's innovation term widens only the covariance a run writes, which the calibration takes
    # off again: an evaluation depends on it, a calibration does not
    monkeypatch.setitem(pipeline.default_config, "innovation_factor", pipeline.default_config["innovation_factor"] + 1)
    assert bench._defaults_key("calibrate") == before["calibrate"]
    assert bench._defaults_key("evaluate") != before["evaluate"]


def test_bench_localises_each_partners_runs_against_the_map(tmp_path, monkeypatch):
    """With two partner worlds a map meets four wrong runs: each partner's live night and sunny training run,
    copied under its own name, each row naming the world it came from."""
    from scenesig.benchmarks import integrity as bench

    calls = []
    monkeypatch.setattr(bench, "wrong_copy", lambda world, src, alias: (calls.append((src, alias)), src)[1])
    monkeypatch.setattr(bench, "localise_one", lambda layout, seed, run, kind, cond, mode, every:
                        {"run": run.name, "kind": kind, "condition": cond, "localisations": 0})
    layout = bench.Layout(tmp_path, "tiny", 4.0)
    world = bench.localise_world(layout, 1, [2, 3], "evaluate", 1)
    wrong = [r for r in world["runs"] if r["kind"] == "wrong"]
    assert [r["kind"] for r in world["runs"]].count("right") == 5
    assert [r["from_seed"] for r in wrong] == [2, 2, 3, 3] and world["wrong_runs_from_seeds"] == [2, 3]
    names = layout.run_names()
    assert [(src, alias) for src, alias in calls] == [
        (layout.runs(2) / names[6], "drive1"), (layout.runs(2) / names[0], "drive2"),
        (layout.runs(3) / names[6], "drive3"), (layout.runs(3) / names[0], "drive4")]
    assert [r["condition"] for r in wrong] == ["night", "sunny"] * 2


def test_bench_does_not_reuse_a_wrong_run_cached_from_another_world(tmp_path):
    """The partner world follows the seed list: a wrong-map copy (and its localisations) cached from another
    world's run is replaced, a copy of the same run is kept."""
    from scenesig.benchmarks.integrity import wrong_copy

    def run(name):
        d = tmp_path / name
        (d / "images").mkdir(parents=True)
        (d / "odometry.csv").write_text(name)
        (d / "run.toml").write_text(f'name = "{name}"\nconditions = ["night"]\n[metadata]\nseed = 1\n')
        return d

    a, b, world = run("a"), run("b"), tmp_path / "world"
    dst = wrong_copy(world, a, "drive1")
    assert (dst / "odometry.csv").read_text() == "a" and "metadata" not in (dst / "run.toml").read_text()
    cached = world / "loc-calibrate" / "drive1"
    cached.mkdir(parents=True)
    (cached / "row.json").write_text("{}")
    assert wrong_copy(world, a, "drive1") == dst and cached.exists()      # same source: the cache stands
    wrong_copy(world, b, "drive1")
    assert (dst / "odometry.csv").read_text() == "b" and not cached.exists()


def test_bench_chooses_the_camera_checks_inlier_minimum():
    """A correct run whose poorly supported turns (20 inliers) agree on a wrong ratio is refused until the
    minimum excludes them; the miscalibrated run, well supported, is refused throughout."""
    from scenesig.benchmarks.integrity import camera_verdicts, choose_min_inliers

    rows = [{"seed": 1, "run": "fog", "focal_scale": 1.0, "turns": [[1.0, 40]] * 5 + [[1.5, 20]] * 20},
            {"seed": 1, "run": "fog", "focal_scale": 0.5, "turns": [[2.0, 60]] * 8}]
    v15 = camera_verdicts(rows, 15)
    assert v15["correct"]["refused"] == 1 and v15["correct_refused_runs"] == ["1/fog"]
    v25 = camera_verdicts(rows, 25)
    assert v25["correct"]["passed"] == 1 and v25["miscalibrated"]["refused"] == 1
    assert camera_verdicts(rows, 50)["correct"]["no_verdict"] == 1      # too few turns left to judge
    assert choose_min_inliers(rows) == 25


def test_choose_meets_the_targets_on_synthetic_streams(monkeypatch):
    from scenesig.benchmarks import integrity
    from scenesig.benchmarks.integrity import choose

    # a 64-point grid of the same keys (the full one is 2160 points): the rule is under test, not the grid
    monkeypatch.setattr(integrity, "GRID", {k: v[:2] for k, v in integrity.GRID.items()})

    rng = np.random.default_rng(3)
    rates = {p: (OWN, OTHER) for p in range(100)}

    def stream(rate, residual):
        return [FrameStats(0.2 * i, i // 5, k, k, SEARCHED, True, residual * (2 * k - 6), max(2 * k - 6, 1),
                           3.0, 0.1) for i, k in enumerate(rng.binomial(SEARCHED, rate, 80))]

    streams = ([{"kind": "right", "stats": stream(0.45, 1.0), "rates": rates} for _ in range(3)]
               + [{"kind": "wrong", "stats": stream(0.08, 1.5), "rates": rates} for _ in range(3)])
    out = choose(streams, alpha=0.01, beta=0.01)
    c, sel = out["chosen"], out["selected"]
    assert c["sprt_max_residual"] >= 1.1 and c["sprt_max_nis"] >= 3.3
    assert out["meets_wrong_target"] and sel["wrong_runs_zero_accepted_rate"] == 1.0
    assert sel["right_runs_with_alert_rate"] == 0.0 and sel["right_accepted"] > 150
    # the realised per-probation error rates are measured and reported beside the design
    assert out["probations"]["missed_detection_rate"] == 0.0 and out["probations"]["false_alarm_rate"] <= 0.05
    from scenesig.localiser.integrity import default_config

    assert out["probations"]["design"] == {"false_alarm": 0.01, "missed_detection": 0.01,
                                           "lookalike_places": default_config["sprt_lookalike_places"]}
    # the grid replayed by two processes gives the same grid and choice
    twice = choose(streams, alpha=0.01, beta=0.01, jobs=2)
    assert twice["grid"] == out["grid"] and twice["chosen"] == c
    # the per-probation count was made for the points tied on the alert rate, the chosen one among them
    assert sel["wrong_probations"] > 0 and sel["wrong_probations_accepted"] == 0


def test_select_prefers_the_setting_that_refuses_more_wrong_map_probations():
    """The rule's order: the wrong-map target first, then the fewest right runs alerting, then the fewest
    wrong-map probations accepted (a probation started at every solved frame), and only then the frames
    accepted: a setting that accepts more right-map frames but lets one look-alike through a probation loses
    to one that refuses it at the same alert rate; a lower alert rate still wins."""
    from scenesig.benchmarks.integrity import GRID, select

    base = {k: v[0] for k, v in GRID.items()}

    def point(alerts, probations, right_accepted, zero=1.0, worst=0, **setting):
        return {**base, **setting, "right_runs_with_alert_rate": alerts, "wrong_runs_zero_accepted_rate": zero,
                "wrong_run_max_accepted": worst, "wrong_accepted": worst, "right_accepted": right_accepted,
                "wrong_probations_accepted": probations}

    four = point(0.05, 1, 14476, sprt_probation_places=4)
    five = point(0.05, 0, 13591, sprt_probation_places=5)
    assert select([four, five]) is five
    fewer_alerts = point(0.042, 3, 12000, sprt_probation_places=3)
    assert select([four, five, fewer_alerts]) is fewer_alerts
    # a point that misses the wrong-map target is not chosen however few alerts it raises
    missing = point(0.0, 0, 20000, worst=4, sprt_probation_places=2)
    assert select([four, five, missing]) is five
    # points whose probations were not counted (not tied on the alert rate) rank after counted ones
    uncounted = {k: v for k, v in five.items() if k != "wrong_probations_accepted"}
    assert select([four, uncounted]) is four


def test_live_streams_reads_every_defaults_wrong_map_streams_once(tmp_path):
    """The wrong-map streams localised live under today's defaults and under earlier ones are all calibration
    data (each met other look-alikes); a stream recorded identically under two keys counts once, right-map
    runs and rows without statistics are not read."""
    import json
    from dataclasses import asdict

    from scenesig.benchmarks.integrity import Layout, live_folder, live_streams

    layout = Layout(tmp_path, "compact", 5.0)

    def record(folder, run, kind, inliers):
        d = layout.world(7) / folder / run
        d.mkdir(parents=True)
        (d / "row.json").write_text(json.dumps({"run": run, "kind": kind}))
        stats = [FrameStats(0.2 * i, 0, inliers, inliers, SEARCHED, True, 1.0, 1.0, 1.0, 0.1, 2.0 * i)
                 for i in range(5)]
        (d / "integrity_stats.json").write_text(json.dumps([asdict(s) for s in stats]))

    today = live_folder(layout, 7).name
    record(today, "drive1", "wrong", 3)
    record("loc-evaluate-0000000000", "drive1", "wrong", 3)      # the same stream under an older key
    record("loc-evaluate-0000000000", "drive2", "wrong", 5)      # another look-alike's chance
    record("loc-evaluate-1111111111", "drive2", "wrong", 4)
    (layout.world(7) / "loc-evaluate-1111111111" / "drive3").mkdir()   # refused before statistics were kept
    streams = live_streams(layout, 7)
    assert [(s["run"], s["stats"][0].inliers) for s in streams] == [("drive1", 3), ("drive2", 5), ("drive2", 4)]
    assert streams[0]["dir"].parent.name == today


def test_replay_begins_a_new_probation_after_the_localiser_searched():
    """The monitor records only tracked frames, so a gap in a recorded stream is a stretch the localiser spent
    searching: the frame after it follows a new global fix, whose probation starts afresh, as it does live.
    Carried across the gap, the evidence and the odometry span of places before it would pass a probation
    on one place after it."""
    from scenesig.benchmarks.integrity import run_outcome, searched_before

    rates = {p: (OWN, OTHER) for p in range(40)}
    cfg = {**DESIGN, "sprt_probation_places": 4}
    k = int(OWN * SEARCHED)

    def frame(t, od):
        return FrameStats(t, int(od // 10), k, k, SEARCHED, True, np.nan, 1.0, np.nan, np.nan, od)

    before = [frame(0.2 * i, 2.0 * i) for i in range(15)]              # three units: probation not done
    after = [frame(20.0 + 0.2 * i, 200.0 + 2.0 * i) for i in range(5)]   # one unit, after a search
    stream = before + after
    assert searched_before(stream).tolist() == [False] * 15 + [True] + [False] * 4
    assert run_outcome(stream, rates, cfg) == (0, 0)
    # the same frames without the gap: one probation over four units, accepted
    joined = before + [frame(3.0 + 0.2 * i, 30.0 + 2.0 * i) for i in range(5)]
    assert run_outcome(joined, rates, cfg)[0] > 0


def test_choose_without_tracking_windows_keeps_the_backstops():
    """Right-map streams too short for a single tracking window (nothing tracked 4 frames): the backstops
    have no data and keep their defaults instead of failing."""
    from scenesig.benchmarks.integrity import choose
    from scenesig.localiser.integrity import default_config

    short = [FrameStats(0.2 * i, 0, 10, 10, SEARCHED, True, 10.0, 14.0, 3.0, 0.1) for i in range(2)]
    out = choose([{"kind": kind, "stats": short, "rates": {0: (OWN, OTHER)}} for kind in ("right", "wrong")],
                 alpha=0.01, beta=0.01)
    assert out["chosen"]["sprt_max_residual"] == default_config["sprt_max_residual"]
    assert out["chosen"]["sprt_max_nis"] == default_config["sprt_max_nis"] and out["right_windows"] == 0


def test_bound_model_uses_the_innovations_when_they_explain_the_errors():
    """Synthetic runs whose errors are the marginal's noise, but in a third of them a stretch where the
    errors (and the fixes' innovations) are a metre: the marginal alone needs a large inflation on every
    run to cover those; the innovation term covers them where they are, so the chosen model has a factor
    above 0, a smaller median bound, covers its share of the runs it was chosen on and holds out on
    random halves of the worlds."""
    from scenesig.benchmarks.integrity import _mean_last, choose_bound_model

    rng = np.random.default_rng(5)
    runs = []
    for i in range(40):
        n = 200
        sigma = np.full(n, 0.2)                           # Z·σ of the marginal: errors of σ ≈ 0.1 m
        scale = np.full(n, 0.1)
        innovations = np.abs(rng.normal(0.0, 0.15, n))
        if i % 3 == 0:                                    # a stretch of metre errors that the fixes show
            scale[:60] = 1.0
            innovations[:60] = np.abs(rng.normal(1.0, 0.2, 60))
        err = np.abs(rng.normal(0.0, scale))
        runs.append({"seed": i // 5, "run": f"r{i}", "err": err, "sigma": sigma,
                     "innovations": innovations, "upto": np.arange(1, n + 1)})
    out = choose_bound_model(runs, halvings=50, assurance=0.9)   # 8 synthetic worlds: the 10th percentile
    grid = {(g["window"], g["factor"], g["share"]): g for g in out["grid"]}
    plain = grid[(5, 0.0, out["share"])]                  # the marginal alone, covering the same share
    assert out["factor"] > 0 and out["held_out_low"] >= 0.95 and out["admissible"] > 0
    assert out["covered_rate"] >= out["share"] and out["median_bound_m"] < 0.8 * plain["median_bound_m"]
    # a share met exactly on the calibration runs holds out less often than a larger one
    same = [grid[(out["window"], out["factor"], share)] for share in (0.95, 0.99)]
    assert same[0]["held_out_mean"] <= same[1]["held_out_mean"]
    # the window mean is the localiser's: the last ``window`` innovations up to each frame
    assert _mean_last(np.array([1.0, np.nan, 3.0, 5.0]), np.array([0, 1, 3, 4]), 2).tolist() == [0.0, 1.0, 3.0, 4.0]


@pytest.mark.heavy
def test_bench_runs_end_to_end_on_the_tiny_preset(tmp_path):
    """Two tiny worlds: simulated, built (with firing rates), localised right and wrong; the JSON's shape."""
    from scenesig.benchmarks.integrity import main

    out = tmp_path / "r.json"
    assert main(["--seeds", "7-8", "--evaluate", "--preset", "tiny", "--camera-hz", "4", "--cache",
                 str(tmp_path / "cache"), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert [w["seed"] for w in doc["worlds"]] == [7, 8] and not doc["failed_worlds"]
    kinds = [r["kind"] for r in doc["worlds"][0]["runs"]]
    assert kinds.count("right") == 5 and kinds.count("wrong") == 2
    for r in doc["worlds"][0]["runs"]:
        assert {"localisations", "false_fixes", "integrity_alerts", "bound_coverage_95", "lateral_bound_95_m",
                "failures", "condition"} <= set(r)
    s = doc["summary"]
    for key in ("wrong_runs_zero_accepted_rate", "wrong_run_max_accepted", "right_runs_with_alert_rate",
                "right_runs_coverage_ok_rate"):
        assert key in s
    assert (tmp_path / "cache" / "tiny-4hz" / "seed7" / "map" / "firing.json").exists()
    # the wrong-world runs are stripped copies: no metadata, no name, no condition to read
    toml = (tmp_path / "cache" / "tiny-4hz" / "seed7" / "wrong" / "drive1" / "run.toml").read_text()
    assert "[metadata]" not in toml and 'name = "drive1"' in toml and "unknown" in toml
    # a rerun resumes from the cache: the same rows, nothing recomputed
    out2 = tmp_path / "r2.json"
    assert main(["--seeds", "7-8", "--evaluate", "--preset", "tiny", "--camera-hz", "4", "--cache",
                 str(tmp_path / "cache"), "--json", str(out2)]) == 0
    assert json.loads(out2.read_text())["worlds"] == doc["worlds"]


def test_camera_check_refuses_only_when_the_medians_interval_is_beyond_the_refuse_ratio():
    """A refusal needs the distribution-free 90 % interval of the median turn ratio wholly beyond 1.25: a
    correctly calibrated fog run's scattered turns (2102's, median 2.82 over 7) give a warning, a halved
    focal length's agreeing turns an error."""
    from scenesig.mapping.camera_check import calibration_finding, median_interval

    x = np.arange(1.0, 17.0)
    assert median_interval(x[:4], 0.9) is None                     # 4 values: even the range is < 90 %
    assert median_interval(x[:5], 0.9) == (1.0, 5.0)               # 1 - 2/32 = 0.9375
    assert median_interval(x[:7], 0.9) == (1.0, 7.0)               # (x2, x6) covers only 0.875
    assert median_interval(x, 0.9) == (5.0, 12.0)                  # 1 - 2 P(B <= 4), B ~ Bin(16, 1/2): 0.923
    fog = [[r, 40] for r in (0.43, 1.14, 1.15, 2.82, 4.36, 7.40, 11.43)]
    finding, ratio, n = calibration_finding(fog)
    assert (ratio, n) == (2.82, 7) and finding.severity == "warning" and "not refused" in finding.reason
    halved = [[r, 60] for r in (1.87, 1.93, 1.98, 2.0, 2.01, 2.04, 2.08, 2.1)]
    finding, ratio, _ = calibration_finding(halved)
    assert finding.severity == "error" and 1.9 < ratio < 2.1
    doubled = [[r / 4, 60] for r, _ in halved]                       # the images turn half as much
    assert calibration_finding(doubled)[0].severity == "error"
