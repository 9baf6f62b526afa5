"""``scenesig demo --lifelong``: the lifelong-map stage, after the demo (it reuses the demo's world).

The base map is either the demo's map (``--lifelong-map demo``: six training conditions) or a map of
the demo's *day* training runs only (``--lifelong-map day``, the default: sunny and overcast, as a
vehicle first surveyed in daylight would have). A condition that base map never trained on (night on
the day map, autumn on the demo's, by default) is then learned:

1. simulate two runs of it, A and B, beside the demo's runs (run numbers after the demo's, so their
   drives differ from every training run's);
2. localise A and B against the base map (scene signatures; *before*);
3. update a copy of the base map with A (``scenesig map update``, :mod:`scenesig.mapping.update`) into
   ``DIR/lifelong/BASE-CONDITION/map`` -- the base map is left as it was;
4. localise B and one other live run of the demo (the sunny one by default) against the updated map (*after*);
5. ``DIR/lifelong/BASE-CONDITION/result/lifelong.json`` (table rows, the update summary, the targets)
   and ``lifelong.png``, which the report shows in its "Lifelong map" section.

Why the day map by default: measured on the demo world, the demo's own map is not weak anywhere on the
simulator's unseen conditions (autumn, morning sun and fog all give 0.76-0.79 inliers per detection,
the same as the trained conditions), so an update from them adds nothing (``docs/lifelong.md``).

Layout of ``DIR/lifelong``: ``day-map/`` (the day base map, built once), and per stage
``BASE-CONDITION/{localise/{before,after}/RUN/, map/, result/}``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "run_lifelong", "ROW_KEYS"]

default_config = {
    "base": "day",           # "day": a map of the demo's day training runs only; "demo": the demo's map
    "day_conditions": ["sunny", "overcast"],   # the training conditions of the day base map
    # never among the base map's training conditions; None: night on the day map, autumn on the demo's
    "condition": None,
    "other": "sunny",        # the demo's live run checked for regressions after the update
}

#: metrics.json entries of each table row
ROW_KEYS = ("inliers_per_detection_mean", "detections_per_frame_mean", "localised_fraction", "failures")


def _log(msg: str) -> None:
    print(f"[lifelong] {msg}", flush=True)


def _row(label: str, map_name: str, metrics: dict) -> dict:
    lat = metrics.get("lateral_error_map_m") or metrics["lateral_error_m"]
    return {"run": metrics["run"], "label": label, "conditions": metrics["conditions"], "map": map_name,
            "lateral_median_map_m": lat["median"], "lateral_p95_map_m": lat.get("p95"),
            **{k: metrics.get(k) for k in ROW_KEYS}}


def _localise(map_root: Path, run_root: Path, out: Path, every: int) -> dict:
    from scenesig.localiser.replay import localise
    from scenesig.mapping.store import MapStore

    done = out / "metrics.json"
    if done.is_file() and (out / "trajectory.tum").is_file():
        m = json.loads(done.read_text())
        # reused only if made against this map at its current generation
        if "inliers_per_detection_mean" in m and Path(m["map"]).resolve() == Path(map_root).resolve() \
                and m.get("map_generation", 0) == MapStore.open(map_root).generation:
            return m
    return localise(map_root, run_root, out, method="signatures", every=every, progress=False)


def _figure(rows: list[dict], path: Path, updated: list) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scenesig.surveys.io import atomic_path

    labels = [f"{r['label']}\n{r['map']}" for r in rows]
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.6))
    for ax, key, title in zip(axes, ("inliers_per_detection_mean", "lateral_median_map_m", "lateral_p95_map_m",
                                     "failures"),
                              ("inliers per detection", "lateral median vs map (m)", "lateral p95 vs map (m)",
                               "failures")):
        vals = [r.get(key) if r.get(key) is not None else 0.0 for r in rows]
        ax.bar(range(len(rows)), vals, color=["#999" if r["map"] == "before" else "#2a7" for r in rows])
        ax.set_xticks(range(len(rows)), labels, fontsize=7)
        ax.set_ylim(0, max(1.0 if key == "failures" else 0.0, max(vals) * 1.15) or 1.0)
        ax.set_title(title)
    fig.suptitle("Lifelong map: before / after adding run A's weak places "
                 + (f"(places {updated})" if updated else "(no place was weak: nothing added)"))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _day_map(out: Path, train_names: list[str], dcfg: dict, cfg: dict, jobs: int) -> Path:
    """The base map of the demo's day training runs (built once into ``DIR/lifelong/day-map``; the
    build resumes or is reused like any ``build_map``), with the demo's reference run."""
    from scenesig.mapping.build import build_map
    from scenesig.surveys.run import read_run

    runs = {n: read_run(out / "world" / n) for n in train_names}
    day = [n for n in train_names if runs[n].conditions[0] in cfg["day_conditions"]]
    ref = train_names[list(dcfg["training"]).index(dcfg["reference"])]
    if ref not in day:
        raise ValueError(f"the demo's reference condition {dcfg['reference']!r} is not among the day conditions")
    path = out / "lifelong" / "day-map"
    if not (path / "build_summary.json").is_file():
        _log(f"0/4 building the day base map from {', '.join(day)} into {path}")
        build_map([runs[n] for n in day], runs[ref], path, jobs=jobs)
    return path


def run_lifelong(out="out/demo", jobs: int = 2, config: dict | None = None, demo_config: dict | None = None) -> dict:
    """The lifelong stage on a finished demo in ``out``; returns ``lifelong.json``'s content."""
    from scenesig.mapping.update import read_localisation, update_map
    from scenesig.surveys.io import atomic_write_text
    from scenesig.surveys.run import read_run
    from scenesig.surveys.sim.simulate import run_names, simulate_run

    from .demo import default_config as demo_defaults

    cfg = merge_settings(default_config, config, "lifelong")
    dcfg = merge_settings(demo_defaults, demo_config, "demo")
    if cfg["base"] not in ("day", "demo"):
        raise ValueError(f"lifelong base map {cfg['base']!r}: choose 'day' or 'demo'")
    trained = list(dcfg["training"]) if cfg["base"] == "demo" else list(cfg["day_conditions"])
    if cfg["condition"] is None:
        cfg["condition"] = "night" if cfg["base"] == "day" else "autumn"
    if cfg["condition"] in trained:
        raise ValueError(f"condition {cfg['condition']!r} is among the {cfg['base']} map's training conditions")
    out = Path(out)
    world, life = out / "world", out / "lifelong" / f"{cfg['base']}-{cfg['condition']}"
    summary = json.loads((world / "simulate_summary.json").read_text())
    names = [r["name"] for r in summary["runs"]]
    n_train = len(dcfg["training"])
    live = names[n_train:]
    base_map = out / "map" if cfg["base"] == "demo" else _day_map(out, names[:n_train], dcfg, cfg, jobs)
    other = next(n for n in live if cfg["other"] in read_run(world / n, check_images=False).conditions)
    every = round(float(dcfg["camera_hz"]) / float(dcfg["detector_hz"]))
    t0 = time.perf_counter()

    _log(f"1/4 simulating two {cfg['condition']} runs (A, B) beside the demo's")
    ab = []
    for k in range(2):
        index = len(names) + k
        name = run_names([cfg["condition"]] * (index + 1))[index]
        if not (world / name / "run.toml").is_file():
            simulate_run(dcfg["preset"], dcfg["seed"], index, cfg["condition"], world,
                         camera_hz=float(dcfg["camera_hz"]), overwrite=True)
        ab.append(name)
    run_a, run_b = ab

    _log(f"2/4 localising {run_a} and {run_b} against the {cfg['base']} map (before)")
    before = {n: _localise(base_map, world / n, life / "localise" / "before" / n, every) for n in ab}
    demo_other = out / "localise" / other / "signatures"
    before[other] = _localise(base_map, world / other,
                              demo_other if cfg["base"] == "demo" and (demo_other / "metrics.json").is_file()
                              else life / "localise" / "before" / other, every)

    _log(f"3/4 updating a copy of the map with {run_a}")
    t = time.perf_counter()
    upd = update_map(base_map, [read_localisation(life / "localise" / "before" / run_a)], out=life / "map",
                     progress=True)
    upd_seconds = time.perf_counter() - t
    if str(upd.get("message", "")).startswith("already applied") and (life / "map" / "update_summary.json").is_file():
        # a re-run of the stage: the figures are those of the update that made this generation
        upd = json.loads((life / "map" / "update_summary.json").read_text())
        upd_seconds = upd.get("seconds", upd_seconds)

    _log(f"4/4 localising {run_b} and {other} against the updated map (after)")
    after = {n: _localise(life / "map", world / n, life / "localise" / "after" / n, every) for n in (run_b, other)}

    rows = [_row("A (used)", "before", before[run_a]),
            _row("B", "before", before[run_b]), _row("B", "after", after[run_b]),
            _row(f"other ({cfg['other']})", "before", before[other]),
            _row(f"other ({cfg['other']})", "after", after[other])]
    b0, b1 = before[run_b], after[run_b]
    ipd0, ipd1 = b0["inliers_per_detection_mean"], b1["inliers_per_detection_mean"]
    build = json.loads((base_map / "build_summary.json").read_text())
    lat = lambda m: (m.get("lateral_error_map_m") or m["lateral_error_m"])["median"]  # noqa: E731
    targets = {
        "B_inliers_per_detection_change": (ipd1 / ipd0 - 1.0) if ipd0 and ipd1 is not None else None,
        "B_inliers_per_detection_up_30pct": bool(ipd0 and ipd1 is not None and ipd1 >= 1.3 * ipd0),
        "B_lateral_median_map_not_worse": lat(b1) <= lat(b0),
        "B_failures_not_more": b1["failures"] <= b0["failures"],
        "other_lateral_median_map_before_after": [lat(before[other]), lat(after[other])],
        "other_failures_before_after": [before[other]["failures"], after[other]["failures"]],
        "update_seconds_per_place": upd["seconds_per_updated_place"],
        "build_seconds_per_place": build.get("seconds_per_place_mean"),
        "bytes_added": upd["bytes_added"],
    }
    result = {"condition": cfg["condition"], "base": cfg["base"], "base_conditions": trained, "run_a": run_a, "run_b": run_b, "other": other, "rows": rows,
              "update": {k: v for k, v in upd.items() if k != "verdicts"}, "update_wall_seconds": upd_seconds,
              "targets": targets, "seconds": time.perf_counter() - t0}
    res_dir = life / "result"
    res_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(res_dir / "lifelong.json", json.dumps(result, indent=1, allow_nan=False) + "\n")
    _figure(rows, res_dir / "lifelong.png", upd["updated"])
    print_table(rows)
    _log(f"targets: {json.dumps(targets)}")
    return result


def print_table(rows: list[dict]) -> None:
    head = (f"{'run':20s} {'map':7s} {'inl/det':>8s} {'det/frame':>9s} {'lat/map m':>9s} {'p95 m':>6s} "
            f"{'localised':>9s} {'failures':>8s}")
    print(head)
    print("-" * len(head))
    f = lambda v, d=2: "-" if v is None else f"{v:.{d}f}"  # noqa: E731
    for r in rows:
        print(f"{r['label'] + ' ' + r['run']:20.20s} {r['map']:7s} {f(r['inliers_per_detection_mean']):>8s} "
              f"{f(r['detections_per_frame_mean']):>9s} {f(r['lateral_median_map_m']):>9s} "
              f"{f(r.get('lateral_p95_map_m')):>6s} "
              f"{f(r['localised_fraction']):>9s} {r['failures']:>8d}")
