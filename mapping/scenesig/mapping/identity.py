"""A map's identity: which map a localisation was made against, so an update never mixes maps.

A map is named by a folder, and folders are renamed, copied and rebuilt; what a localisation
(``metrics.json``) records of its map must name the map itself.  Every map gets, when its build starts,
a random identity (:func:`new_map_id`, a UUID, kept in the build's journal so an interrupted build that
resumes keeps it, and written into ``manifest.json`` as ``map_id``).  A lifelong update
(:mod:`scenesig.mapping.update`) keeps it and counts ``generation`` up, so ``(map_id, generation)`` names one
state of one map.  Two maps built from the same runs with the same settings are two maps: they get two
identities (their contents may be equal; what was localised against which is not).  An update written
elsewhere (``scenesig map update MAP ... --out NEWMAP``) continues the same map: the copy keeps the
identity, and its generation and history tell it from the original.

Maps built before identities existed have no ``map_id``.  They stay readable; their identity is
derived deterministically from what a lifelong update never changes in their manifest
(:func:`derived_map_id`: the camera, extrinsic, build parameters and the places' indices, poses and
neighbours, hashed into a name-based UUID), so every reader of the same map agrees on it, and the first
update writes it into the manifest.  Two such maps built identically would share it -- the one case
identity cannot separate, and the reason new maps draw a random one.
"""
from __future__ import annotations

import hashlib
import json
import uuid

__all__ = ["new_map_id", "derived_map_id", "map_id_of"]

#: namespace of the identities derived for maps built before identities existed
_LEGACY_NAMESPACE = uuid.UUID("6f1c3a52-4d2b-5e8a-9b7c-2a41d0e9c3f7")


def new_map_id() -> str:
    """A fresh identity for a map being built (a random UUID)."""
    return str(uuid.uuid4())


def derived_map_id(doc: dict) -> str:
    """The identity of a map whose manifest ``doc`` has none: a UUID (version 5) of the parts of the
    manifest a lifelong update leaves alone."""
    stable = {
        "format": doc.get("format"),
        "camera": doc.get("camera"),
        "T_vehicle_camera": doc.get("T_vehicle_camera"),
        "params": doc.get("params"),
        "places": [[p.get("index"), p.get("T_world_place"), p.get("neighbours")] for p in doc.get("places", [])],
    }
    digest = hashlib.sha256(json.dumps(stable, sort_keys=True, separators=(",", ":")).encode()).hexdigest()
    return str(uuid.uuid5(_LEGACY_NAMESPACE, digest))


def map_id_of(doc: dict) -> str:
    """The identity a manifest records, else the one derived from it."""
    mid = doc.get("map_id")
    return mid if isinstance(mid, str) and mid else derived_map_id(doc)
