"""Weak places: places of a map with too few scene signatures to localise reliably.

A place's bank localises the vehicle when at least ``min_inliers`` (4) of its signatures are detected
and agree (:mod:`scenesig.localiser.solver`).  Under an appearance the map was not trained on only a fraction of
a bank fires -- at night or in fog often a third or less -- so a place needs several times that many
signatures: a place with fewer than :data:`MIN_SIGNATURES` is *weak*.  ``build-map`` names weak places
(``places_weak`` in ``build_summary.json`` and a warning), ``localise`` warns about those on its route,
and :func:`weak_places` lists them for any map.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["MIN_SIGNATURES", "weak_places", "places_on_route", "weak_places_on_route"]

#: A place with fewer signatures than this is weak.
MIN_SIGNATURES = 10


def _open(map_or_path):
    if isinstance(map_or_path, (str, Path)):
        from scenesig.mapping.store import MapStore
        return MapStore.open(map_or_path)
    return map_or_path


def weak_places(map_or_path, min_signatures: int = MIN_SIGNATURES) -> list[int]:
    """Indices of the places with fewer than ``min_signatures`` signatures.

    Parameters
    ----------
    map_or_path : MapStore or path of a map folder
        Only the manifest is read (it records each place's signature count).
    """
    store = _open(map_or_path)
    return sorted(i for i, m in store.places.items() if m.signatures < int(min_signatures))


def places_on_route(map_or_path, positions: np.ndarray, max_distance_m: float = 10.0) -> list[int]:
    """Places a route passes: the nearest place of each position (N, 2 or 3), within ``max_distance_m``."""
    store = _open(map_or_path)
    if not store.places:
        return []
    idx = np.array(list(store.places), dtype=int)
    xy = np.array([m.position[:2] for m in store.places.values()])
    p = np.asarray(positions, dtype=float).reshape(-1, np.shape(positions)[-1])[:, :2]
    p = p[np.all(np.isfinite(p), axis=1)]
    if not len(p):
        return []
    d = np.linalg.norm(p[:, None, :] - xy[None, :, :], axis=2)
    near = np.argmin(d, axis=1)
    ok = d[np.arange(len(p)), near] <= float(max_distance_m)
    return sorted({int(i) for i in idx[near[ok]]})


def weak_places_on_route(map_or_path, run, min_signatures: int = MIN_SIGNATURES) -> list[int]:
    """Weak places that a survey run passes (by its INS/GPS poses; none known: every weak place)."""
    store = _open(map_or_path)
    weak = weak_places(store, min_signatures)
    if not weak or run.groundtruth_poses is None:
        return weak
    route = set(places_on_route(store, run.groundtruth_poses[:, :3, 3]))
    return [i for i in weak if i in route]
