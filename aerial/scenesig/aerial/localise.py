"""Localise a sequence of UAV images on geo-referenced tiles with MRSM-CC (Jin et al. 2016, §4.4).

Each image is located independently -- scene matching accumulates no drift (§4.5) -- but, as in
the paper's navigation loop (§2), the previous estimate is the next image's rough prior: the
search is limited to ``prior_radius_m`` around it on the tile that holds it.  The first image uses
``prior`` (latitude, longitude) when given; without a prior, or when the previous image could not
be placed, or the estimate near the prior correlates poorly (whole-image NCC below ``min_ncc``),
every tile is searched and the one on which the whole image correlates best wins.

An estimate is reported as a localisation only when it passes the matcher's own checks
(:func:`_verdict`): a finite position, a whole-image NCC of at least ``min_ncc`` on the chosen tile,
and the sensed image's footprint under the estimated transform lying on that tile (at least
``min_coverage`` of it: a query outside every tile can still find a best-correlating spot on one, but
not one that covers it).  Otherwise the image is *not localised*: no position is reported, ``reason``
says which check failed on which tile, and the summary counts and names those images.

Outputs in ``OUT``: ``track.csv`` (image, tile, x_px, y_px, lat, lon, east_m, north_m,
scale, rotation_deg, method, ncc, seconds, localised, coverage, reason, and error_m when the images
folder has a ``truth.csv`` with image, lat, lon), ``track.png`` (the track over the tiles) and
``summary.json``.  Files are written atomically.
"""
from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path

import cv2
import numpy as np

from scenesig.aerial.geo import load_tiles
from scenesig.aerial.landmarks import LandmarkModel
from scenesig.aerial.mrsmcc import MRSMCC
from scenesig.surveys.errors import DataError
from scenesig.surveys.io import atomic_path, atomic_write_text
from scenesig.surveys.settings import merge_settings

__all__ = ["localise_sequence", "IMAGE_SUFFIXES", "COLUMNS"]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")

COLUMNS = ("image", "tile", "x_px", "y_px", "lat", "lon", "east_m", "north_m", "scale",
           "rotation_deg", "method", "ncc", "seconds", "localised", "coverage", "reason")


def footprint_coverage(transform: np.ndarray, sensed_shape, tile_size, n: int = 11) -> float:
    """Share of the sensed image (an n x n grid of points over it) that the sensed -> tile affine maps
    inside the tile (``tile_size`` = (width, height) px)."""
    from scenesig.aerial.affine import apply_affine

    h, w = sensed_shape[:2]
    gx, gy = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    p = apply_affine(transform, np.stack([gx.ravel(), gy.ravel()], axis=1))
    W, H = tile_size
    inside = (p[:, 0] >= -0.5) & (p[:, 0] <= W - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= H - 0.5)
    return float(inside.mean())


def _verdict(loc, tile, sensed_shape, min_ncc: float, min_coverage: float) -> tuple[bool, float, str]:
    """``(localised, coverage, reason)`` of the matcher's estimate ``loc`` on ``tile``: its own checks
    (``min_ncc`` is the NCC bar for this estimate: higher when it is the best of a search of every tile)."""
    if not np.all(np.isfinite(loc.centre)) or not np.all(np.isfinite(loc.transform)):
        return False, 0.0, f"no estimate on any tile (best: {tile.name}, {loc.method})"
    cov = footprint_coverage(loc.transform, sensed_shape, tile.size or tile.image().shape[1::-1])
    why = []
    if not loc.ncc >= min_ncc:
        why.append(f"whole-image NCC {loc.ncc:.3f} < {min_ncc:g}")
    if cov < min_coverage:
        why.append(f"only {100 * cov:.0f} % of the image would lie on the tile (needs {100 * min_coverage:.0f} %)")
    if why:
        return False, cov, f"best match on tile {tile.name} fails its checks: " + "; ".join(why)
    return True, cov, ""


def _read_truth(path: Path, tiles: dict | None = None) -> dict:
    """``{image: (lat, lon)}``; the optional ``tile`` column goes into ``tiles`` (``{image: tile name}``)."""
    truth = {}
    with open(path, newline="") as f:
        for line, row in enumerate(csv.DictReader(f), start=2):
            try:
                truth[row["image"]] = (float(row["lat"]), float(row["lon"]))
            except (KeyError, TypeError, ValueError):
                raise DataError(path, "expected columns image, lat, lon with numbers", line) from None
            if tiles is not None and row.get("tile"):
                tiles[row["image"]] = row["tile"]
    return truth


#: Methods ``localise_sequence`` can use: MRSM-CC, or a point-set-domain stage (:mod:`scenesig.aerial.psd`).
LOCALISE_METHODS = ("mrsmcc", "psd-point", "psd-kdm", "psd-kdmm")


def localise_sequence(tiles_dir, images_dir, out_dir, prior=None, prior_radius_m: float = 30.0,
                      config: dict | None = None, min_ncc: float = 0.2, min_coverage: float = 0.5,
                      progress: bool = True, method: str = "mrsmcc", psd_config: dict | None = None) -> dict:
    """Localise every image of ``images_dir`` (sorted by name) on the tiles of ``tiles_dir``.

    Parameters
    ----------
    tiles_dir : path
        Folder with ``map.csv`` and the tiles.
    images_dir : path
        Sensed images (``.jpg``, ``.png``, ...), in flight order by file name.
    out_dir : path
    prior : (lat, lon), optional
        Rough position of the first image.
    prior_radius_m : float
        Uncertainty of the prior (and of each previous estimate as the next prior).
    config : dict, optional
        Overrides of :data:`scenesig.aerial.mrsmcc.default_config`.
    min_ncc : float
        An estimate near the prior whose whole-image NCC is lower triggers a search of every tile;
        a final estimate below it is not a localisation (``localised`` 0, no position).  An estimate
        found by searching every tile must reach MRSM-CC's ``attitude_min_ncc`` (0.3) too: the best of
        many correlations is high by chance more often than one near a prior.
    min_coverage : float
        Share of the sensed image that must lie on the chosen tile under the estimate; less, and it is
        not a localisation (the image is off the tile, or outside every tile).
    progress : bool
    method : {"mrsmcc", "psd-point", "psd-kdm", "psd-kdmm"}
        ``psd-*``: the point-set-domain stage (:class:`scenesig.aerial.psd.PSDMatcher`) is run on every tile
        and the tile with the best match score wins (for ``psd-kdmm`` the lowest region dissimilarity,
        the seed's decision); the prior is not used.  An estimate is a localisation when its footprint
        covers ``min_coverage`` of the tile.  ``track.csv`` then adds ``score``; with a ``tile`` column
        in ``truth.csv`` the summary counts ``right_tile``.
    psd_config : dict, optional
        Overrides of :data:`scenesig.aerial.psd.default_config` (e.g. the XFeat model file).

    Returns
    -------
    dict
        The summary (also ``OUT/summary.json``).
    """
    from scenesig.aerial.mrsmcc import default_config as mrsmcc_config

    if method not in LOCALISE_METHODS:
        raise ValueError(f"unknown localise method {method!r}; choose from {', '.join(LOCALISE_METHODS)}")
    tiles = load_tiles(tiles_dir)
    search_ncc = float(merge_settings(mrsmcc_config, config, "MR-SMCC")["attitude_min_ncc"])
    images_dir, out = Path(images_dir), Path(out_dir)
    if not images_dir.is_dir():
        raise DataError(images_dir, "images folder not found")
    names = sorted(p for p in images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not names:
        raise DataError(images_dir, f"no images ({', '.join(IMAGE_SUFFIXES)})")
    truth_tiles: dict = {}
    truth = _read_truth(images_dir / "truth.csv", truth_tiles) if (images_dir / "truth.csv").is_file() else {}
    out.mkdir(parents=True, exist_ok=True)
    images = [t.image() for t in tiles]
    psd = method != "mrsmcc"
    if psd:
        from scenesig.aerial.psd import PSDMatcher

        pcfg = {**(psd_config or {}), "stage": method.split("-", 1)[1]}
        matchers = [PSDMatcher(pcfg).fit(im) for im in images]
    landmarks = None if psd else LandmarkModel().fit(images)
    ests: dict[int, MRSMCC] = {}

    def est(i):
        if i not in ests:
            ests[i] = MRSMCC(config, landmarks).fit(images[i])
        return ests[i]

    rows, last = [], (None if prior is None else tuple(float(v) for v in prior))
    it = names
    if progress:
        from tqdm import tqdm
        it = tqdm(names, desc="localising", unit="image")
    for path in it:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise DataError(path, "cannot read or decode image")
        t0 = time.perf_counter()
        if psd:
            rows.append(_locate_psd(matchers, tiles, img, path.name, truth, t0, min_coverage))
            continue
        tile = tiles.tile_at(last) if last is not None else None
        cands = []
        if tile is not None:
            ti = tiles.index(tile.name)
            xy = tile.latlon_to_pixel(last)
            r_px = prior_radius_m / min(tile.metres_per_pixel())
            cands = [(ti, est(ti).locate(img, prior=((xy[0], xy[1]), r_px)))]
        if not cands or not cands[0][1].ncc >= min_ncc:
            # No prior, or lost near it: search every tile.
            cands += [(i, est(i).locate(img)) for i in range(len(tiles))]
        best = max(range(len(cands)), key=lambda k: np.nan_to_num(cands[k][1].ncc, nan=-np.inf))
        ti, loc = cands[best]
        row = {"image": path.name, "tile": tiles[ti].name}
        # the best of a search over every tile is the maximum of many correlations: it must clear the
        # matcher's own bar for trusting a whole-image correlation (attitude_min_ncc), not just min_ncc
        bar = min_ncc if (best == 0 and tile is not None) else max(min_ncc, search_ncc)
        ok, coverage, reason = _verdict(loc, tiles[ti], img.shape, bar, min_coverage)
        if ok:
            ll = tiles[ti].pixel_to_latlon(loc.centre)
            en = tiles.latlon_to_local(ll)
            row.update(x_px=loc.centre[0], y_px=loc.centre[1], lat=ll[0], lon=ll[1],
                       east_m=en[0], north_m=en[1], scale=loc.scale,
                       rotation_deg=loc.rotation_deg)
            last = tuple(ll)
        else:
            row.update({k: float("nan") for k in COLUMNS[2:10]})
            last = None
        row.update(method=loc.method, ncc=loc.ncc, seconds=time.perf_counter() - t0, localised=int(ok),
                   coverage=coverage, reason=reason)
        if truth:
            if path.name in truth and np.isfinite(row["lat"]):
                d = tiles.latlon_to_local(np.array([row["lat"], row["lon"]])) - \
                    tiles.latlon_to_local(np.array(truth[path.name]))
                row["error_m"] = float(np.hypot(*d))
            else:
                row["error_m"] = float("nan")
        rows.append(row)
    cols = list(COLUMNS) + (["score"] if psd else []) + (["error_m"] if truth else [])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols)
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.8f}" if k in ("lat", "lon") else
                        f"{v:.3f}" if isinstance(v, float) else v) for k, v in r.items()})
    atomic_write_text(out / "track.csv", buf.getvalue())
    _plot_track(tiles, rows, truth, out / "track.png")
    located = [r for r in rows if r["localised"]]
    missed = [r for r in rows if not r["localised"]]
    summary = {"images": len(rows), "localised": len(located),
               "localised_fraction": len(located) / len(rows),
               # images the tiles could not place (off every tile, or a match failing its checks), and why
               "not_localised": {r["image"]: r["reason"] for r in missed},
               "seconds_per_image": float(np.mean([r["seconds"] for r in rows]))}
    if missed:
        import logging

        logging.getLogger(__name__).warning(
            "%d of %d images not localised (no tile covers them, or the match failed its checks), e.g. %s: %s",
            len(missed), len(rows), missed[0]["image"], missed[0]["reason"])
    if psd:
        summary["method"] = method
    if truth_tiles:
        summary["right_tile"] = int(sum(r["tile"] == truth_tiles.get(r["image"]) for r in rows if r["localised"]))
    if truth:
        err = np.array([r["error_m"] for r in rows], float)
        summary["median_error_m"] = float(np.nanmedian(err)) if np.isfinite(err).any() else None
        summary["within_10m"] = float(np.mean(np.nan_to_num(err, nan=np.inf) <= 10.0))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    return summary


def _locate_psd(matchers, tiles, img, name, truth, t0, min_coverage) -> dict:
    """One image by a point-set-domain stage on every tile: the best match score picks the tile."""
    locs = [m.locate(img) for m in matchers]
    ti = max(range(len(locs)), key=lambda i: locs[i].score)
    loc, tile = locs[ti], tiles[ti]
    row = {"image": name, "tile": tile.name}
    ok = bool(np.all(np.isfinite(loc.centre)) and np.isfinite(loc.score))
    cov = footprint_coverage(loc.transform, img.shape, tile.size or tile.image().shape[1::-1]) if ok else 0.0
    reason = "" if ok and cov >= min_coverage else (
        f"no estimate on any tile (best: {tile.name})" if not ok else
        f"best match on tile {tile.name} fails its checks: only {100 * cov:.0f} % of the image would lie on it")
    ok = ok and cov >= min_coverage
    if ok:
        ll = tile.pixel_to_latlon(loc.centre)
        en = tiles.latlon_to_local(ll)
        row.update(x_px=loc.centre[0], y_px=loc.centre[1], lat=ll[0], lon=ll[1], east_m=en[0], north_m=en[1],
                   scale=loc.scale, rotation_deg=loc.rotation_deg)
    else:
        row.update({k: float("nan") for k in COLUMNS[2:10]})
    row.update(method=loc.stage, ncc=float("nan"), seconds=time.perf_counter() - t0, localised=int(ok), coverage=cov,
               reason=reason, score=loc.score)
    if truth:
        if name in truth and np.isfinite(row["lat"]):
            d = tiles.latlon_to_local(np.array([row["lat"], row["lon"]])) - tiles.latlon_to_local(np.array(truth[name]))
            row["error_m"] = float(np.hypot(*d))
        else:
            row["error_m"] = float("nan")
    return row


def _plot_track(tiles, rows, truth, path: Path) -> None:
    """The estimated (and true) track in latitude/longitude over the tiles."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    for t in tiles:
        small = cv2.cvtColor(cv2.resize(t.image(), None, fx=0.25, fy=0.25,
                                        interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
        ax.imshow(small, extent=(t.top_left[1], t.bottom_right[1], t.bottom_right[0],
                                 t.top_left[0]), interpolation="bilinear")
    if truth:
        tr = np.array([truth[r["image"]] for r in rows if r["image"] in truth])
        if len(tr):
            ax.plot(tr[:, 1], tr[:, 0], "o-", color="w", ms=3, lw=1, label="truth")
    est = np.array([(r["lat"], r["lon"]) for r in rows], float)
    ok = np.isfinite(est).all(axis=1)
    ax.plot(est[ok, 1], est[ok, 0], "x-", color="r", ms=5, lw=1, label="MRSM-CC")
    lats = [v for t in tiles for v in (t.top_left[0], t.bottom_right[0])]
    lons = [v for t in tiles for v in (t.top_left[1], t.bottom_right[1])]
    ax.set_xlim(min(lons), max(lons))
    ax.set_ylim(min(lats), max(lats))
    ax.set_aspect(1 / np.cos(np.radians(np.mean(lats))))
    ax.set_xlabel("longitude (deg)")
    ax.set_ylabel("latitude (deg)")
    ax.set_title(f"UAV track: {int(ok.sum())} of {len(rows)} images located")
    ax.legend(loc="upper right", fontsize=8)
    ax.ticklabel_format(useOffset=False)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
