"""``scenesig report RESULTS... --out DIR``: one self-contained HTML page of localisation results.

RESULTS are ``scenesig localise`` output folders, or folders containing them (a ``scenesig demo``
folder).  The page (``DIR/index.html``) has

* a summary table -- per run and method: lateral and heading median, localised fraction, failures,
  failures per km, share of distance more than 20 m blind;
* failures per km of each point-feature method relative to scene signatures, per run (the paper's
  finding, in one number per run);
* the localisation figures of §4.3-4.4 (:func:`scenesig.plots.localisation_figures`): per run,
  lateral / heading errors against truth for every method and the raw INS, speed, matches per frame with
  the localised frames marked; the dead-reckoning plot (Fig. 25);
* the matching experiment's figures (Figs 11-14) when a ``matching.json`` is found below RESULTS
  (written by :func:`scenesig.plots.write_matching`).

Figures are PNG files in ``DIR/figures`` referenced by relative links; the page has no script, no
external style sheet and no web font, so it opens anywhere, offline.

Survey runs (for the raw INS errors and the true speed) are found below RESULTS by name, or given with
``--runs``.
"""
from __future__ import annotations

import html
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from scenesig.surveys.errors import DataError
from scenesig.surveys.io import atomic_write_bytes, atomic_write_text, make_dirs

from .experiments import find_localise_outputs, find_runs, read_localise_output, summary_rows
from .plots import localisation_figures

__all__ = ["build_report", "find_matching"]

_CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 1.5em auto; max-width: 1200px;
       color: #222; padding: 0 1em; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; } h2 { font-size: 1.2em; margin-top: 1.8em; border-bottom: 1px solid #ccc; }
p.meta { color: #666; font-size: 0.9em; margin-top: 0; }
table { border-collapse: collapse; font-size: 0.88em; margin: 0.6em 0; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th { background: #f0f0f0; } td.l, th.l { text-align: left; }
tr.sig td { background: #fff5f5; }
td.bad { color: #b00; font-weight: 600; } td.good { color: #070; }
figure { margin: 1em 0 1.6em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.88em; color: #444; margin-top: 0.3em; }
.note { font-size: 0.85em; color: #555; }
"""


def _fmt(v, digits=2, pct=False):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "&ndash;"
    if pct:
        return f"{100 * float(v):.1f} %"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{float(v):.{digits}f}"


def find_matching(paths) -> list[Path]:
    """Folders with a ``matching.json`` (matching-experiment outputs) at or below ``paths``."""
    found = []
    for p in paths:
        p = Path(p)
        if (p / "matching.json").is_file():
            found.append(p)
        elif p.is_dir():
            found.extend(sorted(m.parent for m in p.rglob("matching.json")))
    return list(dict.fromkeys(found))


def _rel(target: Path, start: Path) -> str:
    try:
        return Path(os.path.relpath(Path(target).resolve(), Path(start).resolve())).as_posix()
    except ValueError:        # another drive (Windows): an absolute link is the best we can do
        return Path(target).resolve().as_uri()


def _summary_table(rows: list[dict], out: Path) -> str:
    head = ("<tr><th class='l'>run</th><th class='l'>conditions</th><th class='l'>method</th>"
            "<th>lateral median (m)</th><th>heading median (&deg;)</th>"
            "<th title='relative to the map: without the map&#39;s own georeferencing error'>lateral vs map (m)</th>"
            "<th>localised fraction</th>"
            "<th>failures</th><th>failures / km</th><th>blind &gt; 20 m</th><th>distance (m)</th>"
            "<th title='frames skipped: their image is truncated or corrupt (strict decoding)'>corrupt frames</th>"
            "<th title='real-time replay: stale frames dropped to keep up'>dropped frames</th>"
            "<th title='times the localiser read the INS/GPS'>oracle reads</th>"
            "<th title='distance driven before the first localisation (no GPS: found from the map)'>first fix (m)</th>"
            "<th>relocalisations</th><th title='median distance from lost to found'>relocalise (m)</th>"
            "<th title='accepted localisations more than 5 m from the truth'>false fixes</th>"
            "<th title='median 95 % bound on the lateral error relative to the map (localised frames)'>"
            "lateral bound 95 % (m)</th>"
            "<th title='share of localised frames whose lateral error relative to the map is within their bound "
            "(needs truth)'>bound coverage</th>"
            "<th title='heading error relative to the map (simulated maps)'>heading vs map (&deg;)</th>"
            "<th title='mean solver inliers per detector frame that are signature detections / point matches "
            "(hybrid: both in one solve)'>inliers: signatures / points</th>"
            "<th title='data duration over replay wall time (machine and load dependent)'>real-time factor</th>"
            "<th title='process CPU time per camera frame: less load-sensitive than the wall time'>CPU ms / frame</th>"
            "</tr>")
    body = []
    for r in rows:
        cls = " class='sig'" if r["method"] == "signatures" else ""
        blind = r["blind_fraction_over_20m"]
        bcls = "bad" if blind is not None and blind > 0.01 else "good" if blind is not None else ""
        body.append(
            f"<tr{cls}><td class='l'><a href='{html.escape(_rel(Path(r['folder']), out))}/'>{html.escape(r['run'])}</a></td>"
            f"<td class='l'>{html.escape(', '.join(r['conditions']))}</td><td class='l'>{html.escape(r['method'])}</td>"
            f"<td>{_fmt(r['lateral_median_m'])}</td><td>{_fmt(r['heading_median_deg'])}</td>"
            f"<td>{_fmt(r.get('lateral_map_median_m'))}</td>"
            f"<td>{_fmt(r['localised_fraction'], pct=True)}</td><td>{_fmt(r['failures'])}</td>"
            f"<td>{_fmt(r['failures_per_km'], 1)}</td><td class='{bcls}'>{_fmt(blind, pct=True)}</td>"
            f"<td>{_fmt(r['distance_m'], 0)}</td>"
            f"<td class='{'bad' if r.get('frames_corrupt') else ''}'>{_fmt(r.get('frames_corrupt'))}</td>"
            f"<td>{_fmt(r.get('frames_dropped'))}</td>"
            f"<td>{_fmt(r.get('oracle_reads'))}</td>"
            f"<td>{_fmt(r.get('first_fix_m'), 1)}</td><td>{_fmt(r.get('relocalisations'))}</td>"
            f"<td>{_fmt(r.get('relocalise_median_m'), 1)}</td>"
            f"<td class='{'bad' if r.get('false_fixes') else 'good' if r.get('false_fixes') == 0 else ''}'>"
            f"{_fmt(r.get('false_fixes'))}</td>"
            f"<td>{_fmt(r.get('lateral_bound_95_median_m'))}</td>"
            f"<td class='{_coverage_class(r.get('bound_coverage_95'))}'>"
            f"{_fmt(r.get('bound_coverage_95'), pct=True)}</td>"
            f"<td>{_fmt(r.get('heading_map_median_deg'))}</td>"
            f"<td>{_fmt(r.get('signature_inliers_mean'), 1)} / {_fmt(r.get('point_inliers_mean'), 1)}</td>"
            f"<td>{_fmt(r.get('realtime_factor'), 1)}</td><td>{_fmt(r.get('cpu_ms_per_frame'), 0)}</td></tr>")
    return f"<table id='summary'>{head}{''.join(body)}</table>"


def _coverage_class(c) -> str:
    """An honest bound covers about 95 % of the errors; below 90 % it claims too much."""
    return "" if c is None else "good" if c >= 0.9 else "bad"


def _ratio_table(rows: list[dict]) -> str:
    """Failures per km of each other method relative to signatures, per run."""
    by_run: dict = {}
    for r in rows:
        by_run.setdefault(r["run"], {})[r["method"]] = r
    others = sorted({r["method"] for r in rows} - {"signatures"})
    if "signatures" not in {r["method"] for r in rows} or not others:
        return ""
    head = "<tr><th class='l'>run</th><th class='l'>conditions</th><th>signatures failures / km</th>" + "".join(
        f"<th>{html.escape(m)} failures / km</th><th>{html.escape(m)} / signatures</th>" for m in others) + "</tr>"
    body = []
    tot: dict = {m: [0.0, 0.0] for m in ["signatures"] + others}     # failures, km
    for run, ms in sorted(by_run.items()):
        sig = ms.get("signatures")
        if sig is None:
            continue
        cells = [f"<td class='l'>{html.escape(run)}</td><td class='l'>{html.escape(', '.join(sig['conditions']))}</td>",
                 f"<td>{_fmt(sig['failures_per_km'], 1)}</td>"]
        for m in ["signatures"] + others:
            r = ms.get(m)
            if r is not None and r["failures"] is not None and r["distance_m"]:
                tot[m][0] += r["failures"]
                tot[m][1] += r["distance_m"] / 1000.0
        for m in others:
            r = ms.get(m)
            fk = r["failures_per_km"] if r else None
            sk = sig["failures_per_km"]
            ratio = "&ndash;" if fk is None or sk is None else ("&infin;" if sk == 0 and fk > 0 else
                                                                 "1.0" if sk == 0 else f"{fk / sk:.1f}")
            cells.append(f"<td>{_fmt(fk, 1)}</td><td>{ratio}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    rate = {m: (f / km if km > 0 else None) for m, (f, km) in tot.items()}
    cells = ["<td class='l'><b>all runs</b></td><td></td>", f"<td><b>{_fmt(rate['signatures'], 1)}</b></td>"]
    for m in others:
        fk, sk = rate[m], rate["signatures"]
        ratio = "&ndash;" if fk is None or sk is None else ("&infin;" if sk == 0 and fk > 0 else
                                                             "1.0" if sk == 0 else f"{fk / sk:.1f}")
        cells.append(f"<td><b>{_fmt(fk, 1)}</b></td><td><b>{ratio}</b></td>")
    body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table id='failures'>{head}{''.join(body)}</table>"


def _figure(src: str, caption: str, alt: str) -> str:
    return (f"<figure><img src='{html.escape(src)}' alt='{html.escape(alt)}'>"
            f"<figcaption>{caption}</figcaption></figure>")


def build_report(results, out, runs=None, title: str = "scenesig localisation report") -> Path:
    """Write ``out/index.html`` and ``out/figures/*.png`` from localise outputs (and matching outputs).

    Parameters
    ----------
    results : paths of localise output folders, or folders containing them.
    out : report folder (created; its ``figures/`` is rewritten).
    runs : optional survey-run folders (raw INS errors, true speed); runs below ``results`` are
        found by name anyway.

    Returns
    -------
    Path of ``index.html``.
    """
    t0 = time.perf_counter()
    results = [Path(r) for r in results]
    out = Path(out)
    folders = find_localise_outputs(results)
    if not folders:
        raise DataError(results[0], "no localise outputs (metrics.json) found here")
    outputs = [read_localise_output(f) for f in folders]
    names = {o.run for o in outputs}
    found = find_runs(results, names)
    if runs:
        found.update(find_runs(runs, names))
    # figures are replaced one by one (atomically) and stale ones removed only once the page is
    # written, so a report that fails half way (disk full) leaves the previous page whole
    fig_dir = make_dirs(out / "figures")
    before = {p for p in fig_dir.rglob("*") if p.is_file()}
    figs = localisation_figures(outputs, fig_dir, found)
    produced = {Path(p) for p in figs["runs"].values()} | {Path(figs["dead_reckoning"])}
    rows = summary_rows(outputs)

    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<meta name='viewport' content='width=device-width, initial-scale=1'><style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>",
             f"<p class='meta'>{len(outputs)} localise outputs, {len(names)} runs, methods: "
             f"{html.escape(', '.join(sorted({o.method for o in outputs})))}; generated "
             f"{time.strftime('%Y-%m-%d %H:%M:%S')}.</p>",
             "<h2>Summary</h2>",
             "<p class='note'>Errors against the run's exact truth, lateral across the reference path; "
             "<i>lateral vs map</i>: the same against where the map puts the truth (simulated maps), i.e. "
             "without the map's own georeferencing error, which every method inherits from the survey INS; localised "
             "fraction: share of distance within 10 m of a localisation; a failure is more than 20 m on dead "
             "reckoning (then reset from the INS/GPS; <i>no GPS</i> rows, localised with <code>--oracle none</code>: "
             "declared lost, then relocalised from the map); <i>blind &gt; 20 m</i>: share of distance travelled more "
             "than 20 m past the last localisation (target &le; 1 %). Without GPS the localiser first finds itself "
             "on the map (<i>first fix</i>: distance driven until then, not counted in the errors or the blind "
             "share); <i>false fixes</i>: accepted localisations more than 5 m from the truth.</p>",
             _summary_table(rows, out)]
    ratio = _ratio_table(rows)
    if ratio:
        parts += ["<h2>Failures per km relative to scene signatures</h2>", ratio]
    parts.append("<h2>Distance travelled on dead reckoning (Fig. 25)</h2>")
    parts.append(_figure(_rel(figs["dead_reckoning"], out),
                         "For each distance d, the probability of travelling more than d blind (distance-weighted, "
                         "over all runs of each method); lower left is better.", "dead reckoning"))
    parts.append("<h2>Localisation per run (Figs 15&ndash;24)</h2>")
    for name, p in sorted(figs["runs"].items()):
        conds = next((o.metrics.get("conditions") for o in outputs if o.run == name), None) or []
        ins = "and the raw INS/GPS (dashed) " if name in found else ""
        parts.append(_figure(_rel(p, out),
                             f"<b>{html.escape(name)}</b> ({html.escape(', '.join(conds))}): lateral and heading errors "
                             f"against truth of every method {ins}over distance, speed, matches per frame, and the "
                             f"frames each method localised on.", f"run {name}"))
    matching = find_matching(results)
    for k, mdir in enumerate(matching):
        mfig = fig_dir / (f"matching_{k}" if len(matching) > 1 else "matching")
        make_dirs(mfig)
        pngs = sorted(mdir.glob("*.png"))
        for png in pngs:
            atomic_write_bytes(mfig / png.name, png.read_bytes())
            produced.add(mfig / png.name)
        try:
            summary = json.loads((mdir / "matching.json").read_text()).get("summary", {})
        except (OSError, json.JSONDecodeError) as exc:
            raise DataError(mdir / "matching.json", f"unreadable: {exc}") from None
        parts.append(f"<h2>Feature matching against the map (Figs 11&ndash;14){'' if len(matching) == 1 else f' ({k + 1})'}</h2>")
        if summary:
            runs_ = sorted({r for m in summary.values() for r in m})
            head = "<tr><th class='l'>run</th><th class='l'>conditions</th>" + "".join(
                f"<th>{html.escape(m)}: mean matches / place</th><th>{html.escape(m)}: places matched</th>"
                for m in summary) + "</tr>"
            body = []
            for r in runs_:
                first = next(v[r] for v in summary.values() if r in v)
                cells = [f"<td class='l'>{html.escape(r)}</td><td class='l'>{html.escape(', '.join(first['conditions']))}</td>"]
                for m, v in summary.items():
                    e = v.get(r, {})
                    cells.append(f"<td>{_fmt(e.get('matches_mean'), 1)}</td><td>{_fmt(e.get('places_with_match'), pct=True)}</td>")
                body.append("<tr>" + "".join(cells) + "</tr>")
            parts.append(f"<table class='matching'>{head}{''.join(body)}</table>")
        for png in pngs:
            cap = ("Matches per place (a match: the same feature within 15 px in the ground-truth aligned live "
                   "frame and the map keyframe), one line per test run." if "counts" in png.name else
                   "Where matches fall: +1 per pixel inside each matched shape, averaged over the test runs.")
            parts.append(_figure(_rel(mfig / png.name, out), cap, png.stem))
    parts += _lifelong_section(results, fig_dir, out)
    parts.append(f"<p class='meta'>Report built in {time.perf_counter() - t0:.1f} s by scenesig.</p></body></html>")
    index = out / "index.html"
    atomic_write_text(out / "report_summary.json",
                      json.dumps({"rows": rows}, indent=1, allow_nan=False, default=_json_default) + "\n")
    atomic_write_text(index, "\n".join(parts))
    for stale in before - produced:      # figures of results no longer on the page
        stale.unlink(missing_ok=True)
    return index


def _lifelong_section(results, fig_dir: Path, out: Path) -> list[str]:
    """The lifelong-map stage (``lifelong.json`` + ``lifelong.png`` at or below ``results``,
    :mod:`scenesig.lifelong`): its table and figure."""
    found = []
    for p in results:
        p = Path(p)
        found += [p / "lifelong.json"] if (p / "lifelong.json").is_file() else sorted(p.rglob("lifelong.json")) if p.is_dir() else []
    parts = []
    for path in dict.fromkeys(found):
        try:
            res = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise DataError(path, f"unreadable: {exc}") from None
        u = res.get("update", {})
        parts += [f"<h2>Lifelong map ({html.escape(res['condition'])}, {html.escape(res.get('base', 'demo'))} map)</h2>",
                  f"<p class='note'>Condition never trained: <b>{html.escape(res['condition'])}</b>; base map: "
                  f"{html.escape(res.get('base', 'demo'))} (trained on "
                  f"{html.escape(', '.join(res.get('base_conditions') or ['the demo runs']))}). Run A "
                  f"({html.escape(res['run_a'])}) was localised and its weak places added to a copy of the map "
                  f"(places {html.escape(str(u.get('updated')))}, generation {u.get('generation')}, "
                  f"{u.get('signatures_added', 0)} signatures, {u.get('bytes_added', 0)} bytes added); run B "
                  f"({html.escape(res['run_b'])}) and another live run localised before and after.</p>"]
        head = ("<tr><th class='l'>run</th><th class='l'>map</th><th>inliers / detection</th><th>detections / frame"
                "</th><th>lateral median vs map (m)</th><th>lateral p95 vs map (m)</th><th>localised</th>"
                "<th>failures</th></tr>")
        body = "".join(
            f"<tr><td class='l'>{html.escape(r['label'])} {html.escape(r['run'])}</td><td class='l'>{html.escape(r['map'])}</td>"
            f"<td>{_fmt(r['inliers_per_detection_mean'])}</td><td>{_fmt(r['detections_per_frame_mean'])}</td>"
            f"<td>{_fmt(r['lateral_median_map_m'])}</td><td>{_fmt(r.get('lateral_p95_map_m'))}</td>"
            f"<td>{_fmt(r['localised_fraction'], pct=True)}</td>"
            f"<td>{_fmt(r['failures'])}</td></tr>" for r in res["rows"])
        parts.append(f"<table class='lifelong'>{head}{body}</table>")
        png = path.parent / "lifelong.png"
        if png.is_file():
            # one figure per stage (DIR/lifelong/BASE-CONDITION/result): named after its stage folder
            target = fig_dir / f"lifelong_{path.parent.parent.name}.png"
            shutil.copy2(png, target)
            parts.append(_figure(_rel(target, out),
                                 "Inliers per detection, lateral median and 95th percentile relative to the map "
                                 "and failures, before (grey) and after (green) the update.", "lifelong"))
    return parts


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    raise TypeError(type(o).__name__)
