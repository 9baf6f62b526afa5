"""``trajectory.png`` of a ``scenesig localise`` output: the estimate on the map, lateral error over distance."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.geometry import interpolate_poses
from scenesig.surveys.io import atomic_path
from scenesig.surveys.localisation import Localisation

from .evaluation import lateral_heading_errors, map_relative_truth, reference_path

__all__ = ["plot_trajectory"]


def plot_trajectory(path: Path, result: Localisation, store: MapStore, ev, metrics: dict) -> None:
    """``trajectory.png``: estimate vs truth vs INS on the map; lateral error over distance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = result.run
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 10), gridspec_kw={"height_ratios": [3, 1.4]})
    places = np.stack([store.places[i].T_world_place for i in sorted(store.places)])
    ax.plot(places[:, 0, 3], places[:, 1, 3], "o", ms=3, color="0.7", label="map places", zorder=1)
    if run.truth_times is not None:
        ax.plot(run.truth_poses[:, 0, 3], run.truth_poses[:, 1, 3], "-", color="k", lw=1.2, label="truth")
    if run.groundtruth_times is not None:
        ax.plot(run.groundtruth_poses[:, 0, 3], run.groundtruth_poses[:, 1, 3], "--", color="tab:orange", lw=1,
                label="INS/GPS")
    ax.plot(result.poses[:, 0, 3], result.poses[:, 1, 3], "-", color="tab:blue", lw=1, label="estimate")
    loc = result.localised
    ax.plot(result.poses[loc, 0, 3], result.poses[loc, 1, 3], ".", ms=3, color="tab:green", label="localised")
    what = "reset" if result.oracle == "ins" else "lost"
    if result.resets.any():
        ax.plot(result.poses[result.resets, 0, 3], result.poses[result.resets, 1, 3], "x", color="tab:red", ms=8,
                mew=2, label=f"{what} ({int(result.resets.sum())})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    lat = (metrics.get("lateral_error_m") or {}).get("median")
    hd = (metrics.get("heading_error_deg") or {}).get("median")
    if metrics.get("truth_source", "none") == "none":
        errors = "no truth"
    else:
        errors = (f"lateral median {'-' if lat is None else f'{lat:.2f} m'}, heading median "
                  f"{'-' if hd is None else f'{hd:.2f}°'}")
    ax.set_title(f"{run.name} [{', '.join(run.conditions)}] -- {result.method}: {errors}, "
                 f"failures {result.failures}"
                 + (f"\nrelative to the map: lateral median {metrics['lateral_error_map_m']['median']:.2f} m, heading "
                    f"median {metrics['heading_error_map_deg']['median']:.2f}° (map georeference error "
                    f"{metrics['map_georeference_error_m']['median']:.1f} m)"
                    if metrics.get("lateral_error_map_m", {}).get("median") is not None else ""), fontsize=10)
    ax.legend(loc="best", fontsize=8)
    s = ev.distance_m
    within = ev.blind_m <= 10.0
    if len(s) > 1:
        # shade the stretches within 10 m of a localisation (the localised_fraction definition)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], within.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            bx.axvspan(s[a], s[min(b, len(s) - 1)], color="tab:green", alpha=0.15, lw=0)
    bound = result.bounds
    if np.isfinite(bound["lateral_bound_95_m"]).any():
        lb = bound["lateral_bound_95_m"]
        bx.fill_between(s, -lb, lb, color="tab:purple", alpha=0.12, lw=0, label="95 % lateral bound")
    if np.isfinite(ev.lateral_m).any():
        bx.plot(s, ev.lateral_m, color="tab:blue", lw=1, label="lateral error")
    tmap = map_relative_truth(store, run.truth_poses) if run.truth_times is not None else None
    if tmap is not None:
        tm = interpolate_poses(run.truth_times, tmap, result.times).reshape(-1, 4, 4)
        lat_map = np.full(len(result.times), np.nan)      # no pose before a first fix without INS/GPS
        if result.valid.any():
            lat_map[result.valid] = lateral_heading_errors(result.poses[result.valid], tm[result.valid],
                                                           reference_path(store))[0]
        bx.plot(s, lat_map, color="tab:purple", lw=1, label="lateral error relative to the map")
    if run.groundtruth_times is not None and run.truth_times is not None:
        ins = interpolate_poses(run.groundtruth_times, run.groundtruth_poses, result.times).reshape(-1, 4, 4)
        tru = interpolate_poses(run.truth_times, run.truth_poses, result.times).reshape(-1, 4, 4)
        ins_lat, _, _ = lateral_heading_errors(ins, tru, reference_path(store))
        bx.plot(s, ins_lat, color="tab:orange", lw=0.8, ls="--", label="INS/GPS lateral error")
    for sr in s[result.resets]:
        bx.axvline(sr, color="tab:red", lw=1)
    bx.axhline(0, color="0.5", lw=0.5)
    if result.oracle != "ins" and result.first_fix_time is not None:
        bx.axvline(float(np.interp(result.first_fix_time, result.times, s)), color="tab:green", lw=1, ls=":")
    along = "truth" if metrics.get("truth_source", "none") != "none" else "odometry"
    bx.set_xlabel(f"distance travelled along the {along} (m)  [green: within 10 m of a localisation; red: {what}"
                  + ("; dotted: first fix from the map" if result.oracle != "ins" else "") + "]")
    bx.set_ylabel("lateral error (m)" if along == "truth" else "lateral bound (m)")
    bx.legend(loc="best", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
