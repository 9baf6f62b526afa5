"""The front door (scenesig.build_map / localise / compare): the CLI's bytes, results in memory, the README.

On the tiny simulated world of ``tests/build_world.py`` (three runs, its cut-down build settings).
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from build_world import CONFIG, map_contents

pytest.importorskip("scenesig.surveys.sim.simulate")

ROOT = Path(__file__).resolve().parents[1]


def _night(runs):
    return next(r for r in runs if r.conditions[0] == "night")


def _json_without_machine(path: Path) -> dict:
    from scenesig.localiser.outputs import TIMING_KEYS

    m = json.loads(path.read_text())
    for k in (*TIMING_KEYS, "map"):
        m.pop(k, None)
    return m


def test_lazy_exports():
    import scenesig

    assert {"build_map", "localise", "compare"} <= set(dir(scenesig))
    from scenesig import api

    assert scenesig.localise is api.localise and scenesig.compare is api.compare
    with pytest.raises(AttributeError):
        scenesig.no_such_thing  # noqa: B018


def test_api_build_is_the_cli_build(tiny_world, tmp_path):
    from scenesig import api
    from scenesig.cli import main

    runs, library = tiny_world
    paths = [str(r.root) for r in runs]
    assert main(["build-map", *paths, "--reference", paths[0], "--out", str(tmp_path / "cli"), "--config",
                 json.dumps(CONFIG)]) == 0
    summary = api.build_map(paths, paths[0], tmp_path / "api", config=CONFIG, progress=False)
    cli, built = map_contents(tmp_path / "cli"), map_contents(tmp_path / "api")
    assert sorted(cli) == sorted(built)
    for name in cli:
        assert cli[name] == built[name], name
    assert summary["places"] == len([k for k in cli if k.startswith("places/")])
    # the manifest records the resolved build settings (every stage's keys, not only the overrides)
    settings = built["manifest.json"]["params"]["settings"]
    assert settings["frames_per_run"] == 1 and settings["places"]["spacing_m"] == 20.0
    assert settings["mining"]["hog"]["cell"] == 8 and "sweep_max" in settings["refine"]
    assert settings["georeference"]["method"] == "runs"
    # and the library's own build of the same runs is the same map (runs given as objects there)
    assert map_contents(library)["places/place_0000.npz"] == cli["places/place_0000.npz"]


def test_api_localise_is_the_cli_localise(tiny_world, tmp_path):
    from scenesig import api
    from scenesig.cli import main
    from scenesig.localiser.outputs import read_frames_csv
    from scenesig.surveys.localisation import Localisation
    from scenesig.surveys.tum import read_tum

    runs, root = tiny_world
    night = _night(runs)
    assert main(["localise", str(root), str(night.root), "--out", str(tmp_path / "cli")]) == 0
    loc = api.localise(root, night.root)                    # a folder; nothing written
    assert not (tmp_path / "api").exists()
    loc.write(tmp_path / "api")
    for name in ("trajectory.tum", "frames.csv", "covariances.csv"):
        assert (tmp_path / "cli" / name).read_bytes() == (tmp_path / "api" / name).read_bytes(), name
    assert _json_without_machine(tmp_path / "cli" / "metrics.json") == \
        _json_without_machine(tmp_path / "api" / "metrics.json")
    assert (tmp_path / "api" / "trajectory.png").is_file()

    # in memory: times, poses, the per-frame table, the metrics -- the same numbers as the files
    n = len(night.frame_times)
    assert loc.times.shape == (n,) and loc.poses.shape == (n, 4, 4)
    t, P = read_tum(tmp_path / "cli" / "trajectory.tum")
    assert np.allclose(loc.times, t, atol=1e-6) and np.allclose(loc.poses, P.reshape(-1, 4, 4), atol=1e-6)
    frames = read_frames_csv(tmp_path / "cli" / "frames.csv")
    assert list(loc.frames) == list(frames)
    for k in frames:      # the same types; the file's floats are rounded to 6 decimals, memory holds them whole
        assert loc.frames[k].dtype == frames[k].dtype, k
        if frames[k].dtype.kind == "f":
            assert np.allclose(loc.frames[k], frames[k], rtol=0, atol=5.1e-7, equal_nan=True), k
        else:
            assert np.array_equal(loc.frames[k], frames[k]), k
    back = Localisation.from_folder(tmp_path / "api")       # what write() wrote, read back
    assert json.dumps(back.metrics) == json.dumps(loc.metrics) and np.array_equal(back.valid, loc.valid)
    assert np.allclose(back.poses, loc.poses, atol=1e-9, equal_nan=True)
    assert np.allclose(back.planar_covariances, loc.planar_covariances, rtol=1e-12, equal_nan=True)
    m = loc.metrics
    assert m["lateral_error_m"]["median"] is not None and m["truth_source"] == "truth"
    assert m["settings"]["posegraph"]["window_seconds"] > 0 and m["settings"]["replay"]["every"] == 4
    assert m["settings"]["method"]["prior_gating"] is True
    assert "failure_distance_m" in m["settings"]["localiser"]


def test_localise_without_truth_has_no_error_keys(tiny_world):
    import dataclasses

    from scenesig import api

    runs, root = tiny_world
    night = _night(runs)
    # the run as the vehicle has it: INS/GPS (the oracle) but no truth
    run = dataclasses.replace(night, truth_times=None, truth_poses=None, groundtruth_times=None,
                              groundtruth_poses=None)
    with pytest.raises(Exception, match="groundtruth.tum"):      # the oracle is needed with oracle="ins"
        api.localise(root, run)
    loc = api.localise(root, dataclasses.replace(night, truth_times=None, truth_poses=None), every=8)
    m = loc.metrics
    assert m["truth_source"] == "groundtruth"         # the INS/GPS stands in for the truth
    assert m["every"] == 8 and m["settings"]["replay"]["every"] == 8


def test_config_oracle_is_used_and_the_keyword_wins(tiny_world):
    """A key given in ``config`` is used or an error; a keyword given explicitly wins over it (keyword
    > config > preset > default; keywords default to None so an unset one does not override)."""
    import dataclasses

    from scenesig import api

    runs, root = tiny_world
    night = _night(runs)
    blind = dataclasses.replace(night, groundtruth_times=None, groundtruth_poses=None, gps=None)   # no INS/GPS
    with pytest.raises(Exception, match="groundtruth.tum"):         # the default oracle needs the INS/GPS
        api.localise(root, blind)
    m = api.localise(root, blind, config={"oracle": "none"}, every=8).metrics     # config's oracle used
    assert m["oracle"] == "none" and m["settings"]["replay"]["oracle"] == "none"
    with pytest.raises(Exception, match="groundtruth.tum"):         # the explicit keyword over config
        api.localise(root, blind, oracle="ins", config={"oracle": "none"})
    with pytest.raises(ValueError, match="oracle must be one of"):
        api.localise(root, night, config={"oracle": "gps"})
    with pytest.raises(ValueError, match="orcale"):                  # a misspelt key: an error, not ignored
        api.localise(root, night, config={"orcale": "none"})
    with pytest.raises(ValueError, match="oracle must be one of"):
        api.compare(root, [night], methods=["signatures"], config={"oracle": "gps"})


def test_compare_one_row_per_run_and_method(tiny_world):
    from scenesig import api

    runs, root = tiny_world
    night = _night(runs)
    rows = api.compare(root, [night.root, runs[1].root], methods=["signatures", "orb"])
    assert [(r["run"], r["method"]) for r in rows] == [(night.name, "signatures"), (night.name, "orb"),
                                                       (runs[1].name, "signatures"), (runs[1].name, "orb")]
    assert all(list(r)[:2] == ["run", "method"] for r in rows)
    alone = api.localise(root, night.root, method="orb").metrics
    assert rows[1]["lateral_error_m"] == alone["lateral_error_m"] and rows[1]["failures"] == alone["failures"]


def test_presets_reach_the_library(tiny_world):
    from scenesig import api
    from scenesig.presets import PAPER_DIFFERENCES, apply_preset, resolve_settings

    default, paper = resolve_settings(), resolve_settings("paper")

    def flat(d, pre=""):
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{pre}{k}.") if isinstance(v, dict) else {f"{pre}{k}": v})
        return out

    fd, fp = flat(default), flat(paper)
    differ = {k for k in fd if fd[k] != fp[k]} - {"preset"}
    documented = set()
    for d in PAPER_DIFFERENCES:          # every documented difference is there, with the paper's section
        assert d["section"].startswith("McManus et al. 2015, §") and d["why"]
        if d["stage"] == "localise":     # a method setting: every method that has it
            key = d["key"].split(".", 1)[1]
            hits = {k for k in fd if k.startswith("localise.methods.") and k.endswith("." + key)}
        else:
            hits = {f"{d['stage']}.{d['key']}"}
        assert hits and all(fd[k] == d["default"] and fp[k] == d["paper"] for k in hits), d
        documented |= hits
    assert differ == documented          # ... and nothing else differs
    # the caller's overrides win over the preset's
    assert apply_preset("build", {"frames_per_run": 2}, "paper")["frames_per_run"] == 2
    assert apply_preset("build", None, "default") is None
    with pytest.raises(ValueError, match="unknown preset"):
        apply_preset("build", None, "papr")
    runs, root = tiny_world
    loc = api.localise(root, _night(runs).root, preset="paper", every=8)
    assert loc.metrics["settings"]["method"]["prior_gating"] is False


#: The README's library example is the first ```python block after this marker (an HTML comment, invisible
#: on the rendered page): the README may be rearranged around it, the marker must stay above the block.
README_EXAMPLE_MARKER = "<!-- api-example -->"


def readme_example(text: str) -> str:
    """The code of the README's library example, exactly as printed."""
    found = re.search(re.escape(README_EXAMPLE_MARKER) + r"\s*```python\n(.*?)```", text, re.S)
    assert found, f"README.md has no ```python block right after {README_EXAMPLE_MARKER!r}"
    return found.group(1)


def test_readme_example_runs(tiny_world, tmp_path, monkeypatch):
    """The README's notebook-style example, run exactly as printed in a folder holding the tiny world.

    The only patch: the build gets this suite's cut-down *speed* settings (fewer places, shapes and
    frames; tests/build_world.py) -- never ``layers`` or anything else that decides which calls
    succeed, and only where the README gives no settings of its own."""
    import scenesig
    from scenesig import api

    code = readme_example((ROOT / "README.md").read_text(encoding="utf-8"))
    runs, _ = tiny_world
    (tmp_path / "world").mkdir()
    for r in runs:
        (tmp_path / "world" / r.root.name).symlink_to(r.root)
    speed = {k: v for k, v in CONFIG.items() if k != "layers"}
    real = api.build_map

    def build_faster(*args, **kwargs):
        assert "config" not in kwargs, "the README passes build settings: the speed patch would replace them"
        return real(*args, **kwargs, config=speed, progress=False)

    monkeypatch.setattr(api, "build_map", build_faster)
    monkeypatch.chdir(tmp_path)
    scope = {"__name__": "readme"}
    exec(compile(code, "README.md", "exec"), scope)
    assert isinstance(scope["loc"], api.Localisation) and scope["summary"]["places"] >= 2
    assert (tmp_path / "out" / "night" / "frames.csv").is_file()
    assert math.isfinite(scope["loc"].metrics["lateral_error_m"]["median"])
    assert scope["row"]["method"] == "orb"      # compare's last row: the method whose layer the example asks for
    assert scenesig.build_map is build_faster    # the example went through the front door


def test_readme_example_is_found_by_its_marker():
    text = "# T\n\n" + README_EXAMPLE_MARKER + "\n```python\nx = 1\n```\n\n```python\ny = 2\n```\n"
    assert readme_example(text) == "x = 1\n"
    with pytest.raises(AssertionError, match="api-example"):
        readme_example("```python\nx = 1\n```\n")


def test_config_show_and_bad_settings_at_the_cli(capsys, tmp_path):
    from scenesig.cli import main

    assert main(["config", "show", "--preset", "paper"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["preset"] == "paper" and doc["build"]["georeference"]["method"] == "reference"
    assert set(doc) == {"preset", "build", "localise", "update", "experiment"}
    assert set(doc["localise"]["methods"]) >= {"signatures", "orb", "sift", "orb-all", "sift-all"}
    assert main(["config", "show", "--preset", "paper", "--differences"]) == 0
    assert len(json.loads(capsys.readouterr().out)) >= 4
    # a misspelt option: exit 2 naming it, nothing written
    with pytest.raises(SystemExit) as exc:
        main(["build-map", str(tmp_path / "r"), "--reference", str(tmp_path / "r"), "--out", str(tmp_path / "m"),
              "--config", '{"refine": {"huber_alfa": 1}}'])
    assert exc.value.code == 2 and "huber_alfa" in capsys.readouterr().err and not (tmp_path / "m").exists()
    with pytest.raises(SystemExit) as exc:
        main(["localise", str(tmp_path / "m"), str(tmp_path / "r"), "--out", str(tmp_path / "o"),
              "--config", '{"localiser": {"posegraph": {"failure_distance_m": 5}}}'])
    assert exc.value.code == 2 and "failure_distance_m" in capsys.readouterr().err


def test_config_show_lists_every_registered_method_resolved(capsys, monkeypatch):
    """``config show`` takes its methods from the registry, each with its resolved settings (before: a
    hard-coded list, and ``{}`` for the hybrid and XFeat methods)."""
    from scenesig.cli import main
    from scenesig.localiser import methods as registry
    from scenesig.localiser.hybrid import default_config as hybrid_default
    from scenesig.localiser.pointmethod import default_config as point_default

    def settings(config=None):                      # a method registered by someone else, with its resolver
        out = {"threshold": 0.5, "prior_gating": True, **(config or {})}
        if set(out) - {"threshold", "prior_gating"}:
            raise ValueError(f"unknown my-method option(s) {sorted(set(out) - {'threshold', 'prior_gating'})}")
        return out

    monkeypatch.setitem(registry._METHODS, "my-method", object)
    monkeypatch.setitem(registry._SETTINGS, "my-method", settings)
    assert main(["config", "show"]) == 0
    methods = json.loads(capsys.readouterr().out)["localise"]["methods"]
    assert set(methods) == set(registry.available_methods()) and "my-method" in methods
    assert methods["my-method"] == {"threshold": 0.5, "prior_gating": True}
    for name in ("hybrid", "hybrid-orb", "hybrid-sift-all", "hybrid-orb-all"):
        assert set(hybrid_default) <= set(methods[name]), name
        assert methods[name]["points"]["point_map"] == ("all" if name.endswith("-all") else "reference")
        assert methods[name]["signatures"]["detector"] and methods[name]["solver"]["min_inlier_fraction"] == 0.0
    for name in ("xfeat", "xfeat-all"):
        assert set(point_default) <= set(methods[name]) and methods[name]["match"] == "mnn", name
    assert methods["orb"]["match"] == "ratio" and methods["sift-all"]["point_map"] == "all"
    # the same resolvers check a replay's method settings
    with pytest.raises(ValueError, match="signature_sigma_scal"):
        registry.method_settings("hybrid", {"signature_sigma_scal": 2.0})
    assert registry.method_settings("not-registered", {"a": 1}) == {"a": 1}     # a localiser object's name
    # the paper preset's whole-image search reaches both parts of a hybrid (before: an unknown-option error)
    assert main(["config", "show", "--preset", "paper"]) == 0
    paper = json.loads(capsys.readouterr().out)["localise"]["methods"]["hybrid"]
    assert paper["signatures"]["prior_gating"] is False and paper["points"]["prior_gating"] is False


def test_missing_extra_is_a_clear_error(tiny_world, monkeypatch, capsys):
    import sys

    from scenesig import api
    from scenesig.cli import main
    from scenesig.surveys.extras import MissingExtraError, require

    monkeypatch.setitem(sys.modules, "distributed", None)        # as if the extra were not installed
    with pytest.raises(MissingExtraError, match=r'scenesig\[distributed\]'):
        require("distributed", "distributed", "a Dask cluster")
    runs, root = tiny_world
    with pytest.raises(MissingExtraError, match="distributed"):
        api.compare(root, [runs[2].root], methods=["signatures"], scheduler="tcp://127.0.0.1:1")
    paths = [str(r.root) for r in runs]
    assert main(["build-map", *paths, "--reference", paths[0], "--out", str(root.parent / "nodask"),
                 "--scheduler", "tcp://127.0.0.1:1", "--config", json.dumps(CONFIG)]) == 2
    assert "pip install" in capsys.readouterr().err and not (root.parent / "nodask").exists()   # nothing written


def test_compare_at_the_cli(tiny_world, capsys, tmp_path):
    from scenesig.cli import main

    runs, root = tiny_world
    assert main(["compare", str(root), str(runs[2].root), "--methods", "signatures", "--every", "8",
                 "--json", str(tmp_path / "rows.json")]) == 0
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [(r["run"], r["method"]) for r in rows] == [(runs[2].name, "signatures")]
    assert rows == json.loads(capsys.readouterr().out)
