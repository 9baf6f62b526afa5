"""The aerial benchmark's ``--measures``: the point-set-domain seed's measures per method
(:mod:`scenesig.aerial.measures` defines them) and the matched pairs / putative match ratio of seeds 002
and 004, collected trial by trial.

Per trial and method: the genuine pair is the sensed image against its own tile (the trial's estimate);
the impostor pair is the same image against another tile, drawn from ``default_rng([seed, trial, 2])``
(the same for every method).  Collected: the match score of both (ROC AUC), the standardised RMSE and
region RMSE of both estimates (RMSE-DI, RRMSE-DI; eq. 19 as printed and d'), and, for methods that
match keypoints, the point measures of the genuine pair (RPR, RR, AR, QR, RT with eps = 3 px).
"""
from __future__ import annotations

import cv2
import numpy as np

from scenesig.aerial import measures as ms

__all__ = ["MeasureCollector", "matching_summary", "DEFINITIONS"]

#: What the JSON's ``measures`` block means (also in docs/aerial.md).
DEFINITIONS = {
    "eps_px": ms.EPS_PX,
    "RPR": "CKN / KN (eq. 13): sensed keypoints whose true tile position is within eps of a tile keypoint",
    "RR": "DTMPN / (DTMPN + UDTMPN) (eq. 14); denominator = sensed keypoints whose true position lies on the tile",
    "AR": "DTMPN / CKN (eq. 15): putative matches within eps of the truth per corresponding keypoint",
    "QR": "KN / IPN (eq. 16)",
    "RT_s": "CPU s of detecting the sensed keypoints + matching them (eq. 17)",
    "RMSE": "eq. 18 on gray levels standardised over the overlap; no estimate = the tile's centre",
    "RRMSE": "eq. 18 within each CI-stable watershed region, averaged",
    "DI": "eq. 19 as printed: |m_g - m_i| / sqrt((s_g + s_i) / 2), s = standard deviations",
    "d_prime": "|m_g - m_i| / sqrt((s_g^2 + s_i^2) / 2)",
    "AUC": "ROC AUC of match scores, genuine (own tile) vs impostor (another tile) pairs",
    "matched_pairs": "putative matches after the method's filter (before RANSAC), mean per trial",
    "putative_match_ratio": "matched pairs / sensed keypoints (seed 004's N_all / N_F), mean per trial",
}


def impostor_tile(n_tiles: int, tile: int, seed: int, index: int) -> int:
    """Another tile than ``tile`` for trial ``index`` of ``seed`` (the same for every method)."""
    j = int(np.random.default_rng([int(seed), int(index), 2]).integers(n_tiles - 1))
    return j + (j >= tile)


def matching_summary(results: list) -> dict:
    """Mean matched pairs and putative match ratio over a method's per-trial results (None when it has none)."""
    mp = [r.matched_pairs for r in results if getattr(r, "matched_pairs", None) is not None]
    kp = [max(1, r.keypoints) for r in results if getattr(r, "matched_pairs", None) is not None]
    if not mp:
        return {"matched_pairs": None, "putative_match_ratio": None}
    return {"matched_pairs": float(np.mean(mp)), "putative_match_ratio": float(np.mean(np.divide(mp, kp)))}


class MeasureCollector:
    """Collects every method's measures over the trials (module docstring)."""

    def __init__(self, images, seed: int):
        self.images = images
        self.seed = int(seed)
        self.rows: dict = {}
        self._labels = None

    def _regions(self, trial):
        if self._labels is None or self._labels[0] is not trial:
            from scenesig.aerial.kdmm import ci_regions

            small = cv2.resize(trial.image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
            lab = ci_regions(small)
            h, w = trial.image.shape[:2]
            self._labels = (trial, cv2.resize(lab.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST))
        return self._labels[1]

    def add(self, method: str, trial, result, estimators) -> dict:
        """Measures of one trial for one method (runs the impostor pair); returns the per-trial record."""
        from scenesig.aerial.trials import sensed_centre

        c = sensed_centre(trial.image.shape)
        to_tile = getattr(trial, "to_tile", None)
        if to_tile is None:
            A = trial.affine
            to_tile = lambda xy, A=A: np.asarray(xy, float) @ A[:, :2].T + A[:, 2]          # noqa: E731
        j = impostor_tile(len(self.images), trial.tile, self.seed, trial.index)
        cv2.setRNGSeed(self.seed * 100003 + trial.index + 7)
        imp = estimators[j].locate(trial.image)
        labels = self._regions(trial)
        rec = {"score_genuine": ms.match_score(result), "score_impostor": ms.match_score(imp)}
        for key, res, t in (("genuine", result, trial.tile), ("impostor", imp, j)):
            tile = self.images[t]
            f = ms.estimate_map(res, tile.shape)
            rec[f"rmse_{key}"] = ms.standardised_rmse(trial.image, tile, f, c)
            rec[f"rrmse_{key}"] = ms.region_rmse(trial.image, tile, f, c, labels)
        pd = getattr(result, "point_data", None)
        if pd:
            H, W = self.images[trial.tile].shape[:2]
            rec["point"] = ms.point_measures(pd["sensed_xy"], pd["tile_xy"], pd["query"], pd["train"], to_tile,
                                             (W, H), trial.image.shape, pd["detect_seconds"], pd["match_seconds"])
        self.rows.setdefault(method, []).append(rec)
        return rec

    def summary(self, method: str) -> dict:
        """The method's measures over its trials (JSON-ready)."""
        rows = self.rows.get(method, [])
        out = {"pairs": len(rows)}
        pts = [r["point"] for r in rows if "point" in r]
        for k in ("RPR", "RR", "AR", "QR", "RT"):
            v = np.array([p[k] for p in pts], float)
            out[k if k != "RT" else "RT_s"] = float(np.nanmean(v)) if len(v) and np.isfinite(v).any() else None
        for name in ("rmse", "rrmse"):
            d = ms.decidability([r[f"{name}_genuine"] for r in rows], [r[f"{name}_impostor"] for r in rows])
            tag = name.upper()
            out[f"{tag}_DI"], out[f"{tag}_d_prime"] = d["DI"], d["d_prime"]
            out[f"{tag}_genuine_mean"], out[f"{tag}_impostor_mean"] = d["genuine_mean"], d["impostor_mean"]
        out["AUC"] = ms.roc_auc([r["score_genuine"] for r in rows], [r["score_impostor"] for r in rows])
        return out
