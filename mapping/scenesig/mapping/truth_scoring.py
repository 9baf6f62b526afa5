"""Simulator-truth scoring of landmarks (the landmark depth errors of ``build_summary.json``).

On a simulated run the simulator's depth buffer gives each kept signature's true depth at the reference
frame; the relative error of the refined landmark depth (McManus et al. 2015, §3.2.1) is recorded per place
in the build stats (``depth_rel_errors``, ``depth_truth_spread``).  On real data there is no truth and
nothing is scored.  Scoring reads the map being built and never changes it.
"""
from __future__ import annotations

import numpy as np

from scenesig.surveys.run import SurveyRun

__all__ = ["landmark_depth_errors"]


def landmark_depth_errors(run: SurveyRun, frame: int, image: np.ndarray, boxes: np.ndarray, ref_size: np.ndarray,
                          ref_scale: np.ndarray, depths: np.ndarray) -> tuple[list, list]:
    """Relative depth error of each landmark against the simulator's truth, and the truth spread of its patch.

    ``boxes`` (n, 2) are the kept classifiers' firing centres at ``frame`` of ``run`` (``image`` its gray
    image), ``ref_size`` (n, 2) / ``ref_scale`` (n,) their size and pyramid scale (NaN where the firing is
    not one the landmark explains), ``depths`` (n,) the refined landmark depths.  Returns two lists over
    the landmarks with a truth (:func:`_true_depths`), both empty for real data.
    """
    rel_err, truth_spread = [], []
    # Detections' (x, y) are window centres in pixel-centre coordinates (pixel i spans i-0.5..i+0.5)
    centre = boxes + 0.5
    box_xyxy = np.concatenate([centre - ref_size / 2, centre + ref_size / 2], axis=1)
    truth = _true_depths(run, frame, image, box_xyxy, ref_scale)
    if truth is not None:
        truth, spread = truth
        ok = np.isfinite(truth) & (truth > 0)
        rel_err = (np.abs(depths[ok] - truth[ok]) / truth[ok]).tolist()
        truth_spread = spread[ok].tolist()
    return rel_err, truth_spread


def _true_depths(run: SurveyRun, frame: int, image: np.ndarray, boxes: np.ndarray, scales: np.ndarray):
    """Ground-truth depth (m) of each signature's patch in a simulated frame, or None for real data.

    A signature is a patch, not a point, and its classifier sees the patch's HOG: image gradients at the
    pyramid level it fired at.  So the reference depth is the median of the simulator's depth buffer over
    the whole firing box, each pixel weighted by the gradient magnitude of ``image`` at that level (sky
    has no depth and is left out; textureless road or wall, which HOG hardly sees, counts little).  The
    spread ``(q75 - q25) / median`` of the same weighted distribution says how far the patch is from
    having one depth (large when it straddles a depth discontinuity).

    Parameters
    ----------
    image : (H, W) gray reference image; boxes : (n, 4) ``x0, y0, x1, y1`` firing boxes (pixels);
    scales : (n,) pyramid scale of each firing.

    Returns
    -------
    (depth, spread) : two (n,) arrays (NaN where the box holds no textured non-sky pixel), or None.
    """
    import cv2

    from scenesig.surveys.sim.truth import depth_image

    depth = depth_image(run, frame)
    if depth is None:
        return None
    out = np.full(len(boxes), np.nan)
    spread = np.full(len(boxes), np.nan)
    h, w = depth.shape
    img = np.asarray(image, dtype=np.float32)
    grads = {}
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        if not (np.isfinite([x0, y0, x1, y1]).all() and np.isfinite(scales[i]) and scales[i] > 0):
            continue
        s = round(float(scales[i]), 4)
        if s not in grads:  # gradient magnitude at the firing's level, brought back to full resolution
            small = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
            g = np.hypot(cv2.Sobel(small, cv2.CV_32F, 1, 0), cv2.Sobel(small, cv2.CV_32F, 0, 1))
            grads[s] = cv2.resize(g, (w, h), interpolation=cv2.INTER_LINEAR)
        r0, r1 = int(max(0, np.floor(y0))), int(min(h, np.ceil(y1)))
        c0, c1 = int(max(0, np.floor(x0))), int(min(w, np.ceil(x1)))
        d = depth[r0:r1, c0:c1].ravel()
        wt = grads[s][r0:r1, c0:c1].ravel()
        ok = np.isfinite(d) & (wt > 0)
        if not ok.any():
            continue
        order = np.argsort(d[ok], kind="stable")
        ds, cw = d[ok][order], np.cumsum(wt[ok][order], dtype=float)
        q25, q50, q75 = ds[np.searchsorted(cw, np.array([0.25, 0.5, 0.75]) * cw[-1]).clip(0, ds.size - 1)]
        out[i], spread[i] = float(q50), float((q75 - q25) / q50)
    return out, spread
