"""Named settings presets (as hloc names its configurations) and every stage's resolved settings.

A preset is a set of overrides per stage -- ``build`` (:data:`scenesig.mapping.build.default_config`),
``localise`` (:data:`scenesig.localiser.replay.default_config`), ``update`` (:data:`scenesig.mapping.update.default_config`)
and ``experiment`` (:data:`scenesig.experiments.default_config`) -- applied *under* a caller's own
overrides (the caller's win).  Two presets:

* ``default`` -- the project's defaults: no overrides.
* ``paper`` -- McManus et al. 2015's values where our defaults differ; :data:`PAPER_DIFFERENCES` lists
  each difference with the paper's section and why our default differs.

:func:`resolve_settings` shows every stage's settings as the library resolves them (``scenesig config
show``); :func:`apply_preset` is what the command line and :mod:`scenesig.api` hand to the library.
"""
from __future__ import annotations

from collections.abc import Mapping

__all__ = ["PRESETS", "PAPER_DIFFERENCES", "STAGES", "apply_preset", "resolve_settings", "preset_names"]

#: Stages a preset may configure (the library's entry points take these overrides).
STAGES = ("build", "localise", "update", "experiment")

#: Each difference of the ``paper`` preset from the defaults: stage, key (dotted), the paper's value, ours,
#: the paper's section and why ours differs.
PAPER_DIFFERENCES = [
    {"stage": "build", "key": "frames_per_run", "paper": 1, "default": None,
     "section": "McManus et al. 2015, §3.2 (Fig. 3) and §4.1",
     "why": "the paper mines each place from one image per training run (31 runs at Begbroke); by default a "
            "map from fewer than six runs takes up to three neighbouring frames per run so that every place "
            "has six images (with six runs or more both give one frame per run)"},
    {"stage": "build", "key": "georeference.method", "paper": "reference", "default": "runs",
     "section": "McManus et al. 2015, §3.1 and §4.1",
     "why": "the paper's places are poses of the reference run's INS; by default each place's pose combines "
            "every training run's INS (mapping.georef), which averages out one run's INS error"},
    {"stage": "build", "key": "layers", "paper": ["signatures", "orb", "sift"], "default": ["signatures"],
     "section": "McManus et al. 2015, §4.2 and §4.3 (the point-feature system)",
     "why": "the paper's maps serve its point-feature baseline too, matched against the map image of each place "
            "(the reference run's keyframe: the orb and sift layers); by default a map holds what the default "
            "method needs, and build-map --layers adds the baselines' layers"},
    {"stage": "localise", "key": "method.prior_gating", "paper": False, "default": True,
     "section": "McManus et al. 2015, §3.3.1 and §3.3.2",
     "why": "the paper runs the place's bank of classifiers over the live image (OpenCV's GPU HOG) and uses the "
            "motion prior in the solver (eq. 10); by default the detector searches only windows around the "
            "projections the prior predicts, which is faster and rejects distant false firings"},
]


def _paper() -> dict:
    out: dict = {}
    for d in PAPER_DIFFERENCES:
        node = out.setdefault(d["stage"], {})
        *path, last = d["key"].split(".")
        for k in path:
            node = node.setdefault(k, {})
        node[last] = d["paper"]
    return out


#: preset name -> stage -> overrides
PRESETS = {"default": {}, "paper": _paper()}


def preset_names() -> list[str]:
    return list(PRESETS)


def _deep_merge(base: Mapping, top: Mapping) -> dict:
    out = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in base.items()}
    for k, v in top.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def apply_preset(stage: str, config: Mapping | None = None, preset: str | None = None) -> dict | None:
    """``config`` (a stage's overrides) on top of preset ``preset``'s overrides of that stage.

    Returns None when both are empty (the library's defaults).  An unknown preset or stage is a
    ``ValueError`` naming the known ones.
    """
    if stage not in STAGES:
        raise ValueError(f"unknown settings stage {stage!r}; known: {list(STAGES)}")
    if preset is not None and preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; known: {preset_names()}")
    if config is not None and not isinstance(config, Mapping):
        raise TypeError(f"{stage} settings must be a dict, got {type(config).__name__}")
    base = PRESETS[preset or "default"].get(stage, {})
    out = _deep_merge(base, config or {})
    return out or None


def resolve_settings(preset: str | None = None, config: Mapping | None = None) -> dict:
    """Every stage's settings as the library resolves them, with ``preset`` and ``config`` (``{stage:
    overrides}``) applied: ``build`` (:func:`scenesig.mapping.build.resolve_config`), ``localise`` per method
    (:func:`scenesig.localiser.replay.resolve_config`), ``update`` and ``experiment``."""
    from scenesig.experiments import resolve_config as experiment_config
    from scenesig.localiser.pipeline import available_methods
    from scenesig.localiser.replay import resolve_config as replay_config
    from scenesig.mapping.build import resolve_config as build_config
    from scenesig.mapping.update import default_config as update_default
    from scenesig.surveys.settings import merge_settings

    config = dict(config or {})
    unknown = sorted(set(config) - set(STAGES))
    if unknown:
        raise ValueError(f"unknown settings stage(s) {unknown}; known: {list(STAGES)}")
    loc = apply_preset("localise", config.get("localise"), preset)
    methods = {m: replay_config(loc, m)["method"] for m in available_methods()}
    replay = replay_config(loc)
    replay.pop("method")
    return {
        "preset": preset or "default",
        "build": build_config(apply_preset("build", config.get("build"), preset)),
        "localise": {**replay, "methods": methods},
        "update": merge_settings(update_default, apply_preset("update", config.get("update"), preset), "update"),
        "experiment": experiment_config(apply_preset("experiment", config.get("experiment"), preset)),
    }
