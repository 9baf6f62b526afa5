"""The scene-signature weak localiser (McManus et al. 2015, §3.3): the place's classifier bank fired in the image
(:class:`scenesig.localiser.detector.Detector`), then the eq. 10 solver (:mod:`scenesig.localiser.solver`).

:class:`SignatureLocaliser` implements :class:`scenesig.localiser.methods.WeakLocaliser` and is registered as
``signatures``; :data:`signature_default_config` is its settings.
"""
from __future__ import annotations

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.signatures.detection import check_cell_model
from scenesig.signatures.hog import ScaledImages, load_compiled
from scenesig.surveys.geometry import Camera
from scenesig.surveys.settings import merge_settings

from . import _solver_kernel
from .detector import Detector, Observation
from .methods import Measurement, MotionPrior, WeakLocaliser, register_method
from .solver import default_config as solver_default, solve

__all__ = ["signature_default_config", "SignatureLocaliser", "resolve_config"]

#: Settings of the scene-signature method (:class:`SignatureLocaliser`): ``prior_gating`` False searches
#: the whole image on every frame instead of the windows around the projections the motion prior predicts.
signature_default_config = {
    "detector": {},                  # overrides of localiser.detector.default_config
    "solver": {},                    # overrides of localiser.solver.default_config
    "prior_gating": True,
}


def resolve_config(config: dict | None = None) -> dict:
    """Every setting of the scene-signature method: ``config`` (overrides of
    :data:`signature_default_config`) with its detector's and solver's defaults."""
    from .detector import default_config as detector_default

    cfg = merge_settings(signature_default_config, config, "signature method", open=("detector", "solver"))
    cfg["detector"] = merge_settings(detector_default, cfg["detector"], "detector")
    cfg["solver"] = merge_settings(solver_default, cfg["solver"], "solver")
    return cfg


class SignatureLocaliser(WeakLocaliser):
    """Scene signatures: the place's bank fired in the image (detector), eq. 10 (solver).

    Parameters
    ----------
    store : the map.
    camera, T_vehicle_camera : the live camera.
    config : ``{"detector": {...}, "solver": {...}, "prior_gating": bool}``: overrides of
        :data:`scenesig.localiser.detector.default_config` and :data:`scenesig.localiser.solver.default_config`;
        ``prior_gating`` False searches the whole image on every frame instead of the windows
        around the projections the motion prior predicts.
    """

    name = "signatures"

    def __init__(self, store: MapStore, camera: Camera, T_vehicle_camera: np.ndarray, config: dict | None = None):
        # The detector and the solver check their own sub-dicts (their default_config).
        cfg = merge_settings(signature_default_config, config, "signature method", open=("detector", "solver"))
        self.prior_gating = bool(cfg["prior_gating"])
        self.store = store
        self.camera = camera
        self.T_vehicle_camera = np.asarray(T_vehicle_camera, dtype=float)
        self.solver_config = merge_settings(solver_default, cfg["solver"], "solver")
        self.detector = Detector(store, camera, T_vehicle_camera, cfg["detector"])
        self.color = False
        self._hog = None
        load_compiled()                # before the replay's clock starts, like opening the map
        if self.solver_config["compiled"]:
            _solver_kernel.warm_up()
        # The banks' HOG parameters decide gray or colour input (all places share them).
        for idx in store.places:
            lp = self.detector.place(idx)
            if len(lp.bank):
                self._hog = dict(lp.bank.hog)
                self.color = bool(self._hog.get("color", False))
                # banks mined on XFeat cells need that network: a missing or different model file
                # stops here, before the replay starts, not at the first detection
                check_cell_model(lp.bank)
                break

    def prefetch(self, place):
        self.detector.prefetch(place)

    def method_config(self) -> dict:
        features = (self._hog or {}).get("features", "hog")
        extra = {}
        if "xfeat" in features:
            from scenesig.signatures.xfeat import get_xfeat
            extra["model_sha256"] = get_xfeat().sha256
        return {"method": self.name, "family": "scene signatures (McManus et al. 2015)",
                "map": "one classifier bank per place, mined from every training run",
                "features": features, **extra,
                "prior_gating": self.prior_gating, "detector": dict(self.detector.config),
                "estimator": "robust Levenberg-Marquardt with the motion prior (eq. 10), Huber",
                "solver": dict(self.solver_config)}

    def prepare(self, image):
        """The image with its HOG pyramid levels' resizes (:class:`scenesig.signatures.hog.ScaledImages`): they
        need neither the place nor the prior, so a replay makes them for the next frame on another
        core; detection then only crops them, with the same features."""
        if self._hog is None:
            return image
        return ScaledImages.for_pyramid(image, self._hog)

    def detect(self, image, place, prior: MotionPrior) -> Observation:
        return self.detector.detect(image, place, prior.T_place_vehicle, prior.covariance,
                                    whole_image=prior.lost or not self.prior_gating,
                                    max_classifiers=prior.max_classifiers)

    def solve(self, obs: Observation, place, prior: MotionPrior) -> Measurement:
        n = len(obs)
        if n < self.solver_config["min_inliers"]:
            return Measurement(None, n, 0, "too_few_detections", obs.ms, 0.0, False,
                               {"whole_image": obs.whole_image, "searched": obs.searched, "signature_inliers": 0})
        res = solve(obs.uv, obs.R, obs.landmarks, prior.T_place_vehicle, prior.covariance, self.camera,
                    self.T_vehicle_camera, landmark_cov=obs.landmark_cov, config=self.solver_config)
        c = res.constraint(self.store.places[place].T_world_place)
        # the inliers' squared Mahalanobis residuals: the integrity monitor's residual test
        r2 = float(np.sum(res.mahalanobis_sq[res.inliers])) if res.n_inliers else float("nan")
        return Measurement(c, n, res.n_inliers, res.reason, obs.ms, res.ms, True,
                           {"whole_image": obs.whole_image, "searched": obs.searched, "residual_chi2": r2,
                            "signature_inliers": res.n_inliers})

    def close(self):
        self.detector.close()


register_method("signatures", SignatureLocaliser, resolve_config)
