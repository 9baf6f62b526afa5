"""Realism check: do point features degrade between simulated conditions the way they do on real data?

For places along the route, a reference view (sunny, run A) is compared with a view of the same
place from another run (its own distractors, sun, clouds, noise; a revisit's pose jitter of up to
~0.4 m and ~1 deg) under each condition.  ORB features (OpenCV, 1000 per image) are matched with the
ratio test (0.8); a match is *consistent with ground truth* when the reference keypoint, lifted to
3-D with the renderer's true depth and reprojected into the other view with the true poses, lands
within 10 px of the matched keypoint.  On real data (McManus et al.; the GRIEF benchmark) point
features match in the hundreds between similar days and collapse at night, in snow and in fog.

Run ``scenesig bench realism --json OUT.json`` (add ``--real`` to also run the same matcher on
the GRIEF images in ``../shared/data/grief`` as a reference).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from scenesig.surveys.geometry import invert
from scenesig.surveys.io import atomic_write_text
from scenesig.surveys.sim.conditions import CONDITIONS
from scenesig.surveys.sim.motion import LANE_CENTRE
from scenesig.surveys.sim.noise import rng_for
from scenesig.surveys.sim.scene import RunScene, default_camera
from scenesig.surveys.sim.views import get_world, view_pose

__all__ = ["orb_consistent_matches", "realism_table", "grief_reference", "main"]


def _orb(nfeatures):
    return cv2.ORB_create(nfeatures=nfeatures)


def orb_consistent_matches(img_a, depth_a, T_a, img_b, T_b, camera, nfeatures: int = 1000, ratio: float = 0.8,
                           tol: float = 10.0) -> dict:
    """ORB ratio-test matches from view A to view B and how many agree with the true geometry."""
    orb = _orb(nfeatures)
    ga = cv2.cvtColor(img_a, cv2.COLOR_BGR2GRAY) if img_a.ndim == 3 else img_a
    gb = cv2.cvtColor(img_b, cv2.COLOR_BGR2GRAY) if img_b.ndim == 3 else img_b
    ka, da = orb.detectAndCompute(ga, None)
    kb, db = orb.detectAndCompute(gb, None)
    res = {"keypoints_a": len(ka), "keypoints_b": len(kb), "matches": 0, "consistent": 0}
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return res
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(da, db, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    res["matches"] = len(good)
    if not good:
        return res
    pa = np.array([ka[m.queryIdx].pt for m in good])
    pb = np.array([kb[m.trainIdx].pt for m in good])
    ia = np.clip(np.round(pa).astype(int), 0, [camera.width - 1, camera.height - 1])
    z = depth_a[ia[:, 1], ia[:, 0]].astype(float)
    rays = camera.rays(pa)
    T_ba = invert(T_b) @ T_a
    far = ~np.isfinite(z)
    Xa = rays * np.where(far, 1.0, z)[:, None]
    # points at infinity (sky) move with the rotation only
    Xb = np.where(far[:, None], Xa @ T_ba[:3, :3].T, Xa @ T_ba[:3, :3].T + T_ba[:3, 3])
    pred, zb = camera.project(Xb)
    ok = np.isfinite(pred).all(1) & (np.linalg.norm(pred - pb, axis=1) <= tol)
    res["consistent"] = int(ok.sum())
    return res


def realism_table(preset: str = "demo", seed: int = 0, places: int = 12, conditions=None, size=None,
                  nfeatures: int = 1000, ratio: float = 0.8, tol: float = 10.0, progress: bool = True) -> dict:
    """Consistent ORB matches, sunny reference vs each condition, averaged over ``places`` places."""
    from tqdm import tqdm

    world = get_world(preset, seed)
    cam = default_camera(size or world.image_size)
    conds = list(conditions) if conditions else list(CONDITIONS)
    L = world.route.drive_length
    ss = np.linspace(0.05 * L, 0.95 * L, places)
    ref = RunScene(world, "sunny", run_key=("realism", "ref"), camera=cam)
    refs = []
    for k, s in enumerate(ss):
        T = view_pose(world, s)
        img, depth = ref.render(T, frame=k, velocity=(8.0, 0.0))
        refs.append((T, img, depth))
    rows = {}
    bar = tqdm(total=len(conds) * places, desc="realism", unit="pair", disable=not progress)
    for c in conds:
        sc = RunScene(world, c, run_key=("realism", c), camera=cam)
        stats = []
        for k, s in enumerate(ss):
            r = rng_for(seed, "realism", c, k)
            T = view_pose(world, s + r.uniform(-0.4, 0.4), LANE_CENTRE + r.uniform(-0.4, 0.4),
                          np.radians(r.normal(0, 0.7)))
            img, _ = sc.render(T, frame=k, velocity=(8.0, 0.0))
            Ta, ia, da = refs[k]
            stats.append(orb_consistent_matches(ia, da, Ta, img, T, cam, nfeatures, ratio, tol))
            bar.update(1)
        m = np.array([x["matches"] for x in stats])
        g = np.array([x["consistent"] for x in stats])
        kp = np.array([x["keypoints_b"] for x in stats])
        rows[c] = {"keypoints": float(kp.mean()), "matches": float(m.mean()), "consistent": float(g.mean()),
                   "consistent_median": float(np.median(g)),
                   "inlier_ratio": float(g.sum() / max(m.sum(), 1)),
                   "places_with_20_consistent": float(np.mean(g >= 20))}
    bar.close()
    day = rows.get("sunny", {}).get("consistent", np.nan)
    for c in rows:
        rows[c]["relative_to_day"] = float(rows[c]["consistent"] / day) if day and day > 0 else None
    return {"preset": preset, "seed": seed, "places": places, "image_size": [cam.width, cam.height],
            "orb_features": nfeatures, "ratio": ratio, "tolerance_px": tol, "reference": "sunny (another run)",
            "rows": rows}


def grief_reference(root: Path, nfeatures: int = 1000, ratio: float = 0.8, tol: float = 20.0) -> dict | None:
    """The same matcher on real images: GRIEF 'season' (summer vs winter, same place), consistency by the
    provided displacement; and stromovka (12 sessions x 5 places, horizontal displacement truth)."""
    out = {}
    season = root / "season"
    if (season / "season_01" / "displacements.txt").is_file():
        disp = np.loadtxt(season / "season_01" / "displacements.txt")
        files0 = sorted((season / "season_00").glob("*.jpg"))
        files1 = sorted((season / "season_01").glob("*.jpg"))
        cons = []
        for k, (f0, f1) in enumerate(zip(files0, files1)):
            a, b = cv2.imread(str(f0), cv2.IMREAD_GRAYSCALE), cv2.imread(str(f1), cv2.IMREAD_GRAYSCALE)
            cons.append(_consistent_shift(a, b, disp[k], nfeatures, ratio, tol))
        out["season_summer_vs_winter"] = {"pairs": len(cons), "consistent_mean": float(np.mean(cons)),
                                          "pairs_with_20": float(np.mean(np.array(cons) >= 20))}
    strom = root / "stromovka"
    if (strom / "ground_truth").is_dir():
        same, diff = [], []
        for place in range(1, 6):
            M = np.loadtxt(strom / "ground_truth" / f"location_{place}.txt")
            imgs = [cv2.imread(str(strom / "images" / f"{s:02d}{place:02d}.jpg"), cv2.IMREAD_GRAYSCALE)
                    for s in range(1, 13)]
            for i in range(12):
                for j in range(12):
                    if i != j and imgs[i] is not None and imgs[j] is not None:
                        c = _consistent_shift(imgs[i], imgs[j], (M[i, j], 0.0), nfeatures, ratio, tol, horizontal=True)
                        (same if abs(i - j) == 1 else diff).append(c)
        out["stromovka_adjacent_months"] = {"pairs": len(same), "consistent_mean": float(np.mean(same))}
        out["stromovka_other_months"] = {"pairs": len(diff), "consistent_mean": float(np.mean(diff))}
    return out or None


def _consistent_shift(a, b, shift, nfeatures, ratio, tol, horizontal=False):
    orb = _orb(nfeatures)
    ka, da = orb.detectAndCompute(a, None)
    kb, db = orb.detectAndCompute(b, None)
    if da is None or db is None:
        return 0
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(da, db, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    if not good:
        return 0
    pa = np.array([ka[m.queryIdx].pt for m in good])
    pb = np.array([kb[m.trainIdx].pt for m in good])
    d = pb - pa - np.asarray(shift, float)
    err = np.abs(d[:, 0]) if horizontal else np.linalg.norm(d, axis=1)
    return int((err <= tol).sum())


def format_table(result: dict) -> str:
    lines = [f"ORB ({result['orb_features']} features, ratio {result['ratio']}), consistent = within "
             f"{result['tolerance_px']:.0f} px of the true reprojection; reference: {result['reference']}; "
             f"{result['places']} places, {result['image_size'][0]}x{result['image_size'][1]}",
             "| sunny vs | matches | consistent (mean) | median | inlier ratio | places >= 20 | vs day |",
             "|---|---|---|---|---|---|---|"]
    for c, r in result["rows"].items():
        rel = f"{r['relative_to_day']:.2f}" if r.get("relative_to_day") is not None else "-"
        lines.append(f"| {c} | {r['matches']:.0f} | {r['consistent']:.0f} | {r['consistent_median']:.0f} | "
                     f"{r['inlier_ratio']:.2f} | {100 * r['places_with_20_consistent']:.0f} % | {rel} |")
    real = result.get("real")
    if real:
        lines.append("")
        lines.append("Real reference (same matcher, GRIEF images 1024x384, consistency within 20 px of the given "
                     "displacement):")
        for k, v in real.items():
            lines.append(f"- {k}: {v['consistent_mean']:.0f} consistent matches per pair ({v['pairs']} pairs)")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scenesig bench realism", description=__doc__.split("\n")[0])
    p.add_argument("--preset", default="demo")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--places", type=int, default=12)
    p.add_argument("--json", type=Path, default=None, help="write the table as JSON here")
    p.add_argument("--real", action="store_true", help="also match the GRIEF images (../shared/data/grief)")
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    res = realism_table(a.preset, a.seed, a.places)
    if a.real:
        root = Path(__file__).resolve().parents[4] / "shared" / "data" / "grief"
        if root.is_dir():
            res["real"] = grief_reference(root)
        else:
            print(f"(no real data at {root}: reference skipped)", file=sys.stderr)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    print(format_table(res))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.json, json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "realism", *sys.argv[1:]]))
