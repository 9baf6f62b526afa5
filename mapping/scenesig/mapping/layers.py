"""Map layers: which localisation methods a map can serve, chosen when it is built.

A place file holds the scene-signature bank (McManus et al. 2015, §3) and, optionally, point-feature
keyframes for the baselines (§4): per family (ORB, SIFT, XFeat) the reference run's keyframe
(``orb``) and/or a keyframe of every training run (``orb-all``).  A layer is named as the method that
uses it, so ``scenesig localise --method sift-all`` needs the ``sift-all`` layer.

The ``signatures`` layer is always built: the bank is what georeferences every place (the training
runs' visual solves, :mod:`scenesig.mapping.georef`), so a map without it has no place poses.  The default
(:data:`DEFAULT_LAYERS`) is what the default method needs: signatures alone.

Maps built before layers were chosen record no ``layers``; theirs follow from the build settings they
record (``points.kinds`` x ``point_maps``, ORB and SIFT in both by default).
"""
from __future__ import annotations

from scenesig.mapping.pointmap import KINDS

__all__ = ["LAYERS", "DEFAULT_LAYERS", "parse_layers", "method_layers", "point_plan", "map_layers",
           "missing_layers", "layer_of_member", "place_layers", "store_layers"]

#: Every layer, in the order they are listed.
LAYERS = ("signatures",) + KINDS + tuple(f"{k}-all" for k in KINDS)
#: What the default method (signatures) needs.
DEFAULT_LAYERS = ("signatures",)
#: hybrid localisation (signatures and point features in one solve, scenesig.localiser.hybrid) needs
#: the signatures and one point layer
HYBRID_LAYERS = {"hybrid": "sift", "hybrid-orb": "orb", "hybrid-sift-all": "sift-all", "hybrid-orb-all": "orb-all"}


def parse_layers(layers) -> list[str]:
    """A layer list (comma-separated text or a sequence) checked, with ``signatures`` added, in
    :data:`LAYERS` order.  ``all`` names every layer.

    Raises
    ------
    ValueError
        An unknown layer (the message lists the known ones).
    """
    if layers is None:
        return list(DEFAULT_LAYERS)
    items = [s.strip() for s in layers.split(",")] if isinstance(layers, str) else [str(s).strip() for s in layers]
    items = [s for s in items if s]
    if "all" in items:
        return list(LAYERS)
    bad = [s for s in items if s not in LAYERS]
    if bad:
        raise ValueError(f"unknown map layer(s) {', '.join(bad)}; choose from {', '.join(LAYERS)} (or 'all')")
    want = set(items) | {"signatures"}
    return [name for name in LAYERS if name in want]


def method_layers(method: str) -> tuple[str, ...]:
    """The layers a localisation method needs (``sift-all`` -> ``("sift-all",)``; a ``-none`` suffix,
    the demo's no-INS/GPS variant of a method, needs what the method needs)."""
    name = method.removesuffix("-none")
    if name in HYBRID_LAYERS:
        return ("signatures", HYBRID_LAYERS[name])
    if name not in LAYERS:
        raise ValueError(f"no map layer serves method {method!r}; layers: {', '.join(LAYERS)}")
    return (name,)


def point_plan(layers) -> dict:
    """Point-feature kinds to build: ``{"reference": [kinds whose reference keyframe is stored],
    "all": [kinds with every run's keyframe], "extract": [kinds to extract at all]}``."""
    layers = parse_layers(layers)
    ref = [k for k in KINDS if k in layers]
    every = [k for k in KINDS if f"{k}-all" in layers]
    return {"reference": ref, "all": every, "extract": [k for k in KINDS if k in ref or k in every]}


def map_layers(params: dict) -> list[str]:
    """The layers a map holds, from its manifest's ``params`` (see the module docstring for old maps)."""
    cfg = (params or {}).get("config") or {}
    if "layers" in cfg:
        return parse_layers(cfg["layers"])
    kinds = (cfg.get("points") or {}).get("kinds", ["orb", "sift"])
    maps = cfg.get("point_maps", ["reference", "all"])
    out = ["signatures"] + [k for k in kinds if "reference" in maps] + [f"{k}-all" for k in kinds if "all" in maps]
    return parse_layers(out)


def place_layers(points: dict) -> list[str]:
    """The layers a place's stored point arrays hold (``signatures`` always)."""
    have = {layer_of_member(f"points/{key}") for key in points if key.endswith("_kp")}
    return [name for name in LAYERS if name == "signatures" or name in have]


def store_layers(store) -> list[str]:
    """The layers a map holds: its first place's (layers are built into every place, and
    ``scenesig map add-layers`` adds to every place), else what its manifest records."""
    if len(store):
        return place_layers(store.load_place(min(store.places)).points or {})
    return map_layers(store.params)


def missing_layers(have, method: str) -> list[str]:
    """Layers ``method`` needs that a map holding the layers ``have`` lacks."""
    return [name for name in method_layers(method) if name not in set(have)]


def layer_of_member(name: str) -> str:
    """The layer (or ``keyframe`` / ``meta``) a place-file member belongs to, for the size accounting."""
    if name.startswith(("bank/", "landmarks", "covariances", "classifier_ids")):
        return "signatures"
    if name.startswith("keyframe"):
        return "keyframe"
    if name.startswith("points/"):
        base = name[len("points/"):]
        if base.startswith("all_T_place_keyframe"):
            return "all_keyframe_poses"          # shared by the -all layers
        for k in KINDS:
            if base.startswith(f"{k}_all_"):
                return f"{k}-all"
            if base.startswith(f"{k}_"):
                return k
    return "meta"
