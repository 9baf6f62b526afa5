"""``scenesig demo`` end to end on the tiny world: every stage runs, summary.json has docs/cli.md's schema,
the report is written, and a re-run reuses what is there.

The default suite runs the demo with the signatures and the hybrid (``--methods signatures,hybrid``: every
stage, the signatures with and without INS/GPS, a point layer); the heavy checks run it with every method."""
import json

import pytest
from conftest import SHARED_MODELS

from scenesig.cli import main
from scenesig.demo import default_config

METRIC_KEYS = {"method", "run", "lateral_error_m", "heading_error_deg", "localised_fraction", "failures",
               "failures_per_km", "blind_fraction_over_20m", "ms_per_detection", "ms_per_solve",
               "ms_per_odometry_update", "realtime_factor", "method_config", "oracle", "oracle_reads", "first_fix_m",
               "relocalisations", "false_fixes", "relocalise_m"}


XFEAT = SHARED_MODELS / "xfeat" / "xfeat.onnx"


def _has_xfeat():
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return XFEAT.is_file()


#: the methods the full demo runs here: xfeat-all only where ../shared/models has the model
METHODS = [m for m in default_config["methods"] if _has_xfeat() or not m.startswith("xfeat")]
#: the default suite's demo: the signatures (with and without INS/GPS) and the hybrid (signatures + SIFT)
QUICK_METHODS = ["signatures", "hybrid"]


def _xfeat_model(out):
    """The model the demo is given: the shared one, or a missing file (the demo then leaves xfeat out)."""
    return str(XFEAT if _has_xfeat() else out / "no-model.onnx")


def _demo(out, methods=None):
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SCENESIG_XFEAT_MODEL", _xfeat_model(out))
        args = ["demo", "--preset", "tiny", "--out", str(out), "--jobs", "2"]
        assert main(args + (["--methods", ",".join(methods)] if methods else [])) == 0
    return out


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    return _demo(tmp_path_factory.mktemp("demo"), QUICK_METHODS)


@pytest.fixture(scope="module")
def demo_full(tmp_path_factory):
    return _demo(tmp_path_factory.mktemp("demo-full"))


def test_summary_schema(demo_out):
    _check_summary(demo_out, QUICK_METHODS)


@pytest.mark.heavy
def test_summary_schema_every_method(demo_full):
    # signatures, the four ORB/SIFT baselines (reference and all-runs point maps), XFeat's and the hybrid
    assert set(default_config["methods"]) == {"signatures", "orb", "sift", "orb-all", "sift-all", "xfeat-all",
                                              "hybrid"}
    _check_summary(demo_full, METHODS)


def _check_summary(demo_out, methods):
    from scenesig.mapping.layers import LAYERS, method_layers

    s = json.loads((demo_out / "summary.json").read_text())
    assert set(s) >= {"runs", "seconds", "localise_seconds_by_method"} and s["seconds"] > 0
    entries = set(methods) | {f"{m}-none" for m in default_config["no_oracle_methods"]}
    assert set(s["localise_seconds_by_method"]) == entries
    # the map holds the layers the demo runs, and no other
    assert s["map"]["layers"] == [name for name in LAYERS if any(name in method_layers(m) for m in methods)]
    assert set(s["map"]["bytes_per_place_by_layer_mean"]) >= set(s["map"]["layers"])
    assert set(s["map"]["seconds_per_place_by_layer_mean"]) == set(s["map"]["layers"])
    assert [r["conditions"] for r in s["runs"]] == [[c] for c in default_config["live"]]
    for r in s["runs"]:
        assert set(r["methods"]) == entries
        for name, m in r["methods"].items():
            assert METRIC_KEYS <= set(m), METRIC_KEYS - set(m)
            method = name.removesuffix("-none")
            assert m["method"] == method and m["run"] == r["run"] and m["method_config"]["method"] == method
            assert m["oracle"] == ("none" if name.endswith("-none") else "ins")
            # the summary holds the localiser's own metrics.json, not a copy that could drift
            on_disk = json.loads((demo_out / "localise" / r["run"] / name / "metrics.json").read_text())
            assert on_disk == m


def test_signatures_localise_every_held_out_run(demo_out):
    """Every held-out run localises without a failure -- except where the integrity monitor refused the
    map's fixes (a false alarm: its calibration on many worlds accepts about one right-map run in eight
    alerting, docs/integrity.md; on the tiny world the fog run does), and never more than one run of five.
    No run, with or without INS/GPS, ever accepts a false fix."""
    s = json.loads((demo_out / "summary.json").read_text())
    alerting = []
    for r in s["runs"]:
        m = r["methods"]["signatures"]
        assert m["false_fixes"] == 0, (r["run"], m["false_fixes"])
        if m["integrity_alerts"]:
            alerting.append(r["run"])
        else:
            assert m["failures"] == 0, (r["run"], m["failures"])
            assert m["blind_fraction_over_20m"] <= 0.01, (r["run"], m["blind_fraction_over_20m"])
        # the hybrid keeps the signatures' robustness (its point inliers keep the monitor's evidence up)
        assert r["methods"]["hybrid"]["failures"] == 0, (r["run"], r["methods"]["hybrid"]["failures"])
        # and without any INS/GPS: found from the map, never wrongly
        m = r["methods"]["signatures-none"]
        assert m["oracle_reads"] == 0 and m["false_fixes"] == 0, (r["run"], m)
        if not m["integrity_alerts"]:
            assert m["first_fix_m"] is not None and m["first_fix_m"] <= 20.0, (r["run"], m["first_fix_m"])
    assert len(alerting) <= 1, alerting


def test_report_and_matching_written(demo_out):
    html = (demo_out / "report" / "index.html").read_text()
    assert "<img" in html
    assert "signatures (no GPS)" in html and "first fix" in html
    assert (demo_out / "matching" / "matching.json").is_file()
    assert (demo_out / "map" / "build_summary.json").is_file()


def test_rerun_reuses_outputs(demo_out, capsys, monkeypatch):
    monkeypatch.setenv("SCENESIG_XFEAT_MODEL", _xfeat_model(demo_out))
    before = {p: p.stat().st_mtime_ns for p in (demo_out / "world").rglob("frames.csv")}
    loc = demo_out / "localise" / "run06_night" / "signatures" / "metrics.json"
    loc_before = loc.read_bytes()
    args = ["demo", "--preset", "tiny", "--out", str(demo_out), "--jobs", "1", "--methods", ",".join(QUICK_METHODS)]
    assert main(args) == 0
    assert "reusing" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in (demo_out / "world").rglob("frames.csv")} == before
    assert loc.read_bytes() == loc_before


@pytest.mark.heavy
def test_lifelong_stage(demo_full):
    """``--lifelong`` after the demo: two unseen-condition runs, the update, before/after rows, the report section."""
    demo_out = demo_full
    assert main(["demo", "--preset", "tiny", "--out", str(demo_out), "--lifelong"]) == 0
    res = json.loads((demo_out / "lifelong" / "day-night" / "result" / "lifelong.json").read_text())
    assert res["base"] == "day" and res["base_conditions"] == ["sunny", "overcast"]
    assert res["condition"] not in res["base_conditions"]
    assert [(r["label"][0], r["map"]) for r in res["rows"]] == [("A", "before"), ("B", "before"), ("B", "after"),
                                                                 ("o", "before"), ("o", "after")]
    assert all(r["inliers_per_detection_mean"] is not None for r in res["rows"])
    assert (demo_out / "lifelong" / "day-night" / "map" / "manifest.json").is_file()
    html = (demo_out / "report" / "index.html").read_text()
    assert "Lifelong map" in html and "lifelong_day-night.png" in html


def test_localise_jobs_share_point_features_by_run_and_kind():
    """A run's ORB entries share one job, its SIFT entries another (one extraction per frame); every other
    entry is its own job; the costliest jobs come first."""
    from scenesig.demo import localise_groups

    entries = ["signatures", "orb", "sift", "orb-all", "sift-all", "signatures-none"]
    jobs = localise_groups([(r, e) for r in ("a", "b") for e in entries])
    assert sorted(map(tuple, (g for _, g in jobs))) == sorted(
        [("orb", "orb-all"), ("sift", "sift-all"), ("signatures",), ("signatures-none",)] * 2)
    assert [g for _, g in jobs[:2]] == [["sift", "sift-all"]] * 2 and {r for r, _ in jobs[:2]} == {"a", "b"}
    assert sorted(e for _, g in jobs for e in g) == sorted(entries * 2)
    # a resumed demo: only what is missing
    assert localise_groups([("a", "sift-all"), ("b", "orb")]) == [("a", ["sift-all"]), ("b", ["orb"])]


def test_demo_localise_benchmark_refuses_to_write_into_the_demo(tmp_path):
    from scenesig.benchmarks.demo_localise import benchmark

    with pytest.raises(ValueError, match="inside the demo folder"):
        benchmark(tmp_path, tmp_path / "again")


@pytest.mark.heavy
def test_demo_localise_benchmark_repeats_the_demo(demo_full, tmp_path):
    """``bench demo_localise --compare`` on the demo: the same localisations, CPU and wall reported."""
    from scenesig.benchmarks.demo_localise import main

    assert main([str(demo_full), "--out", str(tmp_path / "loc"), "--compare", "--json", str(tmp_path / "b.json")]) == 0
    res = json.loads((tmp_path / "b.json").read_text())
    assert res["identical_to_demo"] is True and res["different"] == []
    assert res["cpu_seconds"] > 0 and res["wall_seconds"] > 0 and res["matching_places"] > 0
