"""``scenesig report``: the HTML page renders in headless Chromium with every figure loaded, offline."""
import json
import os
import re
import shutil
import subprocess

import numpy as np
import pytest
from pipeline_world import NothingMethod, TruthMethod, make_live_run, make_map

from scenesig.cli import main
from scenesig.experiments import MatchingResult
from scenesig.plots import write_matching
from scenesig.report import build_report
from scenesig.surveys.errors import DataError

_CHECK = """<script>
window.addEventListener('load', function () {
  var r = [];
  for (const im of document.images) { r.push(im.getAttribute('src') + '=' + im.naturalWidth + 'x' + im.naturalHeight); }
  var p = document.createElement('pre'); p.id = 'imgcheck'; p.textContent = r.join('|'); document.body.appendChild(p);
});
</script>"""


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    msg = ("headless Chromium is needed to check the report renders (Debian: apt-get install -y chromium)")
    if os.environ.get("CI"):
        pytest.fail(msg + " -- it must be installed in CI")
    pytest.skip(msg)


@pytest.fixture(scope="module")
def demo_folder(tmp_path_factory):
    """A small demo-like folder: a map, a run, localise outputs of three methods, a matching experiment."""
    from scenesig.localiser.replay import replay, write_outputs

    base = tmp_path_factory.mktemp("demo")
    store = make_map(base / "map")
    run = make_live_run(base / "runs" / "live", length_m=90.0)
    metrics = {}
    for name, m in (("signatures", TruthMethod(run)), ("orb", TruthMethod(run, blind=[(30.0, 75.0)])),
                    ("sift", NothingMethod())):
        m.name = name
        metrics[name] = write_outputs(replay(store, run, m, every=4), store, base / "localise" / "live" / name,
                                      figure=False)
    P = len(store.places)
    counts = {"signatures": np.full((1, P), 12.0), "orb": np.linspace(0, 30, P)[None], "sift": np.zeros((1, P))}
    counts["orb"][0, 3] = np.nan
    res = MatchingResult(sorted(store.places), ["live"], [["synthetic"]], ["signatures", "orb", "sift"], counts,
                         np.zeros((1, P), int), {m: np.random.default_rng(0).random((P, 6, 8)) for m in counts})
    write_matching(res, store, base / "matching", heat_places=3)
    return base, metrics


def test_report_renders_with_all_figures_in_headless_chromium(demo_folder, tmp_path):
    chromium = _chromium()
    base, metrics = demo_folder
    index = build_report([base], tmp_path / "report")
    page = index.read_text(encoding="utf-8")
    # offline: no script, no external style sheet, font or image
    assert "<script" not in page.lower()
    assert not re.search(r"""(src|href)\s*=\s*['"]?(https?:|//)""", page, re.I)
    assert "<link" not in page.lower()
    srcs = re.findall(r"<img src='([^']+)'", page)
    # dead reckoning + one run + matching counts + 3 heat maps
    assert len(srcs) == 6
    assert all(not s.startswith("/") and (index.parent / s).is_file() for s in srcs)
    # render a copy with a checker script beside it (same folder: the same relative links)
    check = index.parent / "_check.html"
    check.write_text(page.replace("</body>", _CHECK + "</body>"), encoding="utf-8")
    proc = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                           "--disable-dev-shm-usage", "--virtual-time-budget=10000", "--dump-dom", check.as_uri()],
                          capture_output=True, text=True, timeout=120)
    m = re.search(r'<pre id="imgcheck">([^<]*)</pre>', proc.stdout)
    assert m, f"chromium did not run the check (rc {proc.returncode}): {proc.stderr[-2000:]}"
    loaded = dict(item.split("=") for item in m.group(1).split("|"))
    assert sorted(loaded) == sorted(srcs)
    for src, size in loaded.items():
        w, h = (int(v) for v in size.split("x"))
        assert w > 100 and h > 100, (src, size)
    # the summary table carries metrics.json's numbers
    for name, met in metrics.items():
        assert f"<td class='l'>{name}</td><td>{met['lateral_error_m']['median']:.2f}</td>" in page
    rows = json.loads((index.parent / "report_summary.json").read_text())["rows"]
    assert {r["method"] for r in rows} == {"signatures", "orb", "sift"}
    assert next(r for r in rows if r["method"] == "sift")["failures"] == metrics["sift"]["failures"] > 0
    assert "Failures per km relative to scene signatures" in page


def test_a_broken_figure_is_caught_by_the_browser_check(demo_folder, tmp_path):
    """The check itself can fail: a figure that is not an image, or is missing, has naturalWidth 0."""
    chromium = _chromium()
    base, _ = demo_folder
    index = build_report([base / "localise"], tmp_path / "report")
    page = index.read_text(encoding="utf-8")
    srcs = re.findall(r"<img src='([^']+)'", page)
    assert len(srcs) == 2                              # no matching experiment in this selection
    (index.parent / srcs[0]).write_bytes(b"this is not a PNG")
    check = index.parent / "_check.html"
    check.write_text(page.replace("</body>", _CHECK + "</body>"), encoding="utf-8")
    out = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                          "--disable-dev-shm-usage", "--virtual-time-budget=10000", "--dump-dom", check.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    loaded = dict(item.split("=") for item in re.search(r'<pre id="imgcheck">([^<]*)</pre>', out).group(1).split("|"))
    assert loaded[srcs[0]].startswith("0x")
    assert not loaded[srcs[1]].startswith("0x")


def test_report_cli_and_errors(demo_folder, tmp_path, capsys):
    base, _ = demo_folder

    assert main(["report", str(base / "localise" / "live" / "signatures"), str(base / "localise" / "live" / "orb"),
                 "--out", str(tmp_path / "r")]) == 0
    assert "report:" in capsys.readouterr().out
    assert (tmp_path / "r" / "index.html").is_file()
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no localise outputs"):
        build_report([tmp_path / "empty"], tmp_path / "r2")
    with pytest.raises(DataError, match="no such file"):
        build_report([tmp_path / "missing"], tmp_path / "r3")
