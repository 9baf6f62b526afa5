"""Figures and output files of the paper's experiments (McManus et al. 2015, §4): the matching figures
(Figs 11-14) with ``matching.json``, and the localisation figures (Figs 15-25).  The numbers behind them
are computed in :mod:`scenesig.experiments`.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.geometry import interpolate_poses
from scenesig.surveys.io import atomic_path, atomic_write_text, make_dirs
from scenesig.surveys.run import SurveyRun

from .experiments import MatchingResult, dead_reckoning, frame_distances, ins_errors, speed

__all__ = ["METHOD_COLORS", "plot_matching_counts", "plot_matching_heatmaps", "write_matching", "plot_run",
           "plot_dead_reckoning", "localisation_figures"]

#: Method colours, as in the paper where it has them (signatures red, point features green, INS blue).
METHOD_COLORS = {"signatures": "tab:red", "orb": "tab:green", "sift": "tab:olive", "orb-all": "tab:cyan",
                 "sift-all": "tab:brown", "xfeat": "tab:purple", "xfeat-all": "tab:pink", "hybrid": "tab:orange",
                 "hybrid-orb": "tab:gray", "ins": "tab:blue",
                 "truth": "k"}


def _color(method: str, i: int = 0) -> str:
    return METHOD_COLORS.get(method, f"C{i % 10}")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _savefig(fig, path: Path) -> Path:
    path = Path(path)
    make_dirs(path.parent)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    _plt().close(fig)
    return path


def plot_matching_counts(result: MatchingResult, path) -> Path:
    """Figs 11 / 14: matched features per place, one line per test run, one panel per method."""
    plt = _plt()
    n = len(result.methods)
    fig, axes = plt.subplots(n, 1, figsize=(10, 2.6 * n + 0.6), sharex=True, squeeze=False)
    x = np.asarray(result.places)
    for ax, m in zip(axes[:, 0], result.methods):
        for r, name in enumerate(result.runs):
            label = f"{name} ({', '.join(result.conditions[r])})" if result.conditions[r] else name
            ax.plot(x, result.counts[m][r], "-o", ms=2.5, lw=1, label=label, color=f"C{r % 10}")
        ax.set_ylabel(f"{m}\nmatches (< {result.delta_px:g} px)")
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    axes[0, 0].set_title("Feature matches per place against the map (ground-truth aligned frames; gaps: "
                         "the run does not pass the place)", fontsize=10)
    axes[-1, 0].set_xlabel("place")
    axes[0, 0].legend(fontsize=7, ncol=min(4, max(1, len(result.runs))), loc="upper right")
    fig.tight_layout()
    return _savefig(fig, path)


def plot_matching_heatmaps(result: MatchingResult, store: MapStore, method: str, path, n_places: int = 8) -> Path:
    """Figs 12 / 13: map keyframe and mean heat map of matches for sample places, and the average place."""
    import cv2

    plt = _plt()
    heat = result.heat[method]
    P = len(result.places)
    pick = np.unique(np.round(np.linspace(0, P - 1, min(n_places, P))).astype(int)) if P else np.zeros(0, int)
    cols = 4
    n_pairs = len(pick) + 1
    rows = int(np.ceil(n_pairs * 2 / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.1 * cols, 2.0 * rows + 0.5), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    hh, hw = heat.shape[1:] if P else (1, 1)
    vmax = float(np.percentile(heat, 99.5)) if heat.size and heat.max() > 0 else 1.0
    keyframes = []
    for k, j in enumerate(pick):
        kf = store.load_place(result.places[j]).keyframe_image()
        kf = np.zeros((hh, hw), np.uint8) if kf is None else cv2.resize(kf, (hw, hh), interpolation=cv2.INTER_AREA)
        keyframes.append(kf.astype(float))
        a, b = axes.ravel()[2 * k], axes.ravel()[2 * k + 1]
        a.imshow(kf, cmap="gray", vmin=0, vmax=255)
        a.set_title(f"place {result.places[j]}: map", fontsize=8)
        b.imshow(heat[j], cmap="inferno", vmin=0, vmax=vmax)
        b.set_title(f"place {result.places[j]}: {method} matches", fontsize=8)
    a, b = axes.ravel()[2 * len(pick)], axes.ravel()[2 * len(pick) + 1]
    if keyframes:
        a.imshow(np.mean(keyframes, axis=0), cmap="gray", vmin=0, vmax=255)
    a.set_title("average place", fontsize=8)
    b.imshow(heat.mean(axis=0) if P else np.zeros((hh, hw)), cmap="inferno")
    b.set_title(f"average heat map ({method})", fontsize=8)
    fig.suptitle(f"Where {method} matches fall (+1 per pixel inside a matched shape, mean over test runs)",
                 fontsize=10)
    fig.tight_layout()
    return _savefig(fig, path)


def write_matching(result: MatchingResult, store: MapStore, out, heat_places: int = 8) -> dict:
    """``matching.json`` and the figures in ``out``; returns ``{name: path}``."""
    out = Path(out)
    make_dirs(out)
    paths = {"json": out / "matching.json"}
    atomic_write_text(paths["json"], json.dumps(result.to_json(), indent=1, allow_nan=False) + "\n")
    paths["counts"] = plot_matching_counts(result, out / "matching_counts.png")
    for m in result.methods:
        paths[f"heatmap_{m}"] = plot_matching_heatmaps(result, store, m, out / f"matching_heatmap_{m}.png",
                                                       heat_places)
    return paths


def plot_run(outputs: list, path, run: SurveyRun | None = None) -> Path:
    """Figs 15-24 for one run: lateral / heading error, speed, matches per frame, localised frames.

    ``outputs``: the localise outputs of every method on this run; ``run``: the survey run (for the raw
    INS errors, the true speed and distances along the truth), optional.
    """
    plt = _plt()
    outputs = sorted(outputs, key=lambda o: (o.method != "signatures", o.method))
    name = outputs[0].run
    conds = outputs[0].metrics.get("conditions") or (list(run.conditions) if run is not None else [])
    fig, axes = plt.subplots(5, 1, figsize=(11, 12), sharex=True,
                             gridspec_kw={"height_ratios": [2, 2, 1.4, 1.6, 0.25 + 0.25 * len(outputs)]})
    ax_lat, ax_head, ax_v, ax_m, ax_loc = axes
    ins_done = False
    for k, o in enumerate(outputs):
        s = frame_distances(o, run)
        c = _color(o.method, k)
        met = o.metrics
        lat_med = (met.get("lateral_error_m") or {}).get("median")
        lab = o.method + (f" (median |lateral| {lat_med:.2f} m)" if lat_med is not None else "")
        ax_lat.plot(s, o.frames["lateral_error"], color=c, lw=1, label=lab)
        ax_head.plot(s, o.frames["heading_error"], color=c, lw=1, label=o.method)
        ax_v.plot(s, speed(o.times, o.poses), color=c, lw=0.8, label=f"{o.method} estimate")
        det = o.frames["detections"] > 0
        ran = det | (o.frames["inliers"] > 0) | o.localised
        ax_m.plot(s[ran], o.frames["detections"][ran], color=c, lw=0.6, alpha=0.5)
        ax_m.plot(s[ran], o.frames["inliers"][ran], color=c, lw=1.2, label=f"{o.method}: inliers (faint: matches)")
        ax_loc.eventplot([s[o.localised]], lineoffsets=[k], linelengths=0.8, colors=[c], linewidths=0.6)
        if not ins_done and run is not None:
            ins = ins_errors(o, run)
            if ins is not None:
                ax_lat.plot(s, ins[0], color=METHOD_COLORS["ins"], lw=0.9, ls="--", label="INS/GPS (raw)")
                ax_head.plot(s, ins[1], color=METHOD_COLORS["ins"], lw=0.9, ls="--", label="INS/GPS (raw)")
                ins_done = True
            if run.truth_times is not None and not any(l.get_label() == "truth" for l in ax_v.lines):
                tru = interpolate_poses(run.truth_times, run.truth_poses, o.times).reshape(-1, 4, 4)
                ax_v.plot(s, speed(o.times, tru), color="k", lw=1, ls=":", label="truth")
    for ax, lab in ((ax_lat, "lateral error (m)"), (ax_head, "heading error (deg)"), (ax_v, "speed (m/s)"),
                    (ax_m, "matches per frame")):
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right", ncol=2)
    ax_lat.axhline(0, color="0.5", lw=0.5)
    ax_head.axhline(0, color="0.5", lw=0.5)
    ax_m.set_ylim(bottom=0)
    ax_loc.set_yticks(range(len(outputs)))
    ax_loc.set_yticklabels([o.method for o in outputs], fontsize=8)
    ax_loc.set_ylim(-0.6, len(outputs) - 0.4)
    ax_loc.set_xlabel("distance travelled (m)   [bottom: frames each method localised on]")
    title = f"{name}" + (f" [{', '.join(conds)}]" if conds else "")
    fails = ", ".join(f"{o.method} {o.metrics.get('failures', '?')}" for o in outputs)
    ax_lat.set_title(f"Localisation results: {title} -- failures: {fails}", fontsize=10)
    fig.tight_layout()
    return _savefig(fig, path)


def plot_dead_reckoning(curves: dict, d_grid, path) -> Path:
    """Fig. 25: probability of travelling more than d on dead reckoning, per method."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for k, (m, c) in enumerate(sorted(curves.items(), key=lambda kv: (kv[0] != "signatures", kv[0]))):
        ax.plot(d_grid, c["p"], color=_color(m, k), lw=1.8,
                label=f"{m} ({c['runs']} runs, {c['distance_m'] / 1000:.2f} km)")
    ax.axvline(20.0, color="0.5", lw=0.8, ls="--")
    ax.text(20.5, 0.96, "failure: 20 m", fontsize=7, color="0.4", va="top")
    ax.set_xlabel("distance d travelled blind (m)")
    ax.set_ylabel("P(travelling more than d blind)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlim(d_grid[0], d_grid[-1])
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Distance travelled on dead reckoning (all runs; lower left is better)", fontsize=10)
    fig.tight_layout()
    return _savefig(fig, path)


def localisation_figures(outputs: list, out, runs: dict | None = None, d_max: float | None = None) -> dict:
    """Every localisation figure into ``out``: ``run_<name>.png`` per run and ``dead_reckoning.png``.

    Returns ``{"runs": {run: path}, "dead_reckoning": path, "curves": {method: {...}}, "d_grid": list}``.
    """
    out = Path(out)
    make_dirs(out)
    by_run: dict = {}
    for o in outputs:
        by_run.setdefault(o.run, []).append(o)
    paths = {}
    for name, outs in sorted(by_run.items()):
        safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)
        paths[name] = plot_run(outs, out / f"run_{safe}.png", (runs or {}).get(name))
    if d_max is None:
        longest = 0.0
        for o in outputs:
            s = frame_distances(o, (runs or {}).get(o.run))
            if len(s) > 1:
                longest = max(longest, float(s[-1] - s[0]))
        d_max = float(np.clip(longest, 40.0, 100.0))
    d_grid = np.linspace(0.0, d_max, 201)
    curves = dead_reckoning(outputs, d_grid, runs)
    dr = plot_dead_reckoning(curves, d_grid, out / "dead_reckoning.png")
    return {"runs": paths, "dead_reckoning": dr, "curves": curves, "d_grid": d_grid.tolist()}
