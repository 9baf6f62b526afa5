"""Banks from one experience: the settings for a place seen under a single appearance.

McManus et al. (2015, §3.2) mine a place from many runs under different conditions; every filter
that converges has then been trained on real changes of appearance.  With one run (one summer image
of a GRIEF ``sequence`` place, one webcam image at noon, a map built from one survey) mining sees one
appearance and its synthesised copies only.  What helps such a bank is measured in
``docs/single_experience.md``; the settings that were kept are collected here, and every user of
single-experience banks -- the heading benchmark (:mod:`scenesig.signatures.heading`), the webcam benchmark
and the map builder (:mod:`scenesig.mapping.build`) -- applies them through :func:`settings_for` with the
one rule that reads training data only: **the number of real appearances** (runs, sessions, images
that are not synthesised copies) the bank is mined from.  Banks from more appearances take the
paper's path unchanged.
"""
from __future__ import annotations

from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "applies", "settings_for"]

#: Single-experience settings (docs/single_experience.md says what each was chosen on).
default_config = {
    # the rule: a bank mined from at most this many real appearances is a single-experience bank
    "max_appearances": 1,
    # overrides of signatures.mining.default_config for such a bank
    "mining": {},
    # synthetic conditions of the augmented copies (signatures.augment.relight); [] = photometric only
    "conditions": [],
    # detection: local exact histogram matching (5 x 5 windows) of an image to the bank's real
    # training image first, where the caller has that image (benchmarks; not a map's localiser)
    "colour_constancy": False,
}


def _merge(config: dict | None) -> dict:
    return merge_settings(default_config, config, "single-experience", open=("mining",))


def applies(appearances: int, config: dict | None = None) -> bool:
    """True when a bank mined from ``appearances`` real appearances takes the single-experience path."""
    return int(appearances) <= int(_merge(config)["max_appearances"])


def settings_for(appearances: int, mining: dict | None = None, config: dict | None = None) -> dict:
    """What a bank mined from ``appearances`` real appearances is mined with.

    Parameters
    ----------
    appearances : int
        Real training appearances of the place (synthesised copies do not count).
    mining : dict, optional
        The caller's overrides of :data:`scenesig.signatures.mining.default_config`.
    config : dict, optional
        Overrides of :data:`default_config`.

    Returns
    -------
    dict
        ``mining`` (the caller's overrides, plus the single-experience ones when the rule applies),
        ``conditions`` (tuple; empty when it does not), ``colour_constancy`` and ``single`` (bool).
    """
    cfg = _merge(config)
    single = applies(appearances, cfg)
    out = dict(mining or {})
    if single:
        out.update(cfg["mining"])
    return {"mining": out, "conditions": tuple(cfg["conditions"]) if single else (),
            "colour_constancy": bool(cfg["colour_constancy"]) and single, "single": single}
