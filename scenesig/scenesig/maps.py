"""A map's front door: ``scenesig.Map.open(path)`` -- what a map folder holds, in one object.

::

    import scenesig

    m = scenesig.Map.open("maps/demo")
    m.layers                 # ['signatures', 'orb', ...]: what it can localise with (mapping.layers)
    len(m.places), m.places[0].signatures, m.places[0].T_world_place
    m.map_id, m.generation   # its identity (mapping.identity): (map_id, generation) names one state
    m.settings["mining"]     # every build setting, resolved, as the build used it
    m.summary.places_weak    # build_summary.json, typed (None for a map without one)
    m.load_place(0)          # one place's bank, landmarks and keyframe (checksum-verified)

It reads through :class:`scenesig.mapping.store.MapStore` (the one reader of the map format: the manifest
validated, place files checksummed on load, a lifelong update seen through :meth:`Map.refresh`); the store
itself is :attr:`Map.store` for the library functions that take one.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["Map"]


class Map:
    """An opened map folder (see the module docstring); make one with :meth:`open`.

    Attributes
    ----------
    root : the map folder.
    store : the :class:`scenesig.mapping.store.MapStore` reading it.
    """

    def __init__(self, store):
        self.store = store
        self.root = Path(store.root)
        self._summary = None

    @classmethod
    def open(cls, path, verify: bool = False, cache_size: int = 8) -> "Map":
        """Open the map at ``path``; ``verify`` checks every place file's checksum now (else on load).

        A folder that is not a finished map raises :class:`scenesig.surveys.errors.DataError` naming the
        file and what is wrong (the CLI turns it into exit 2).
        """
        from scenesig.mapping.store import MapStore

        return cls(MapStore.open(path, cache_size=cache_size, verify=verify))

    def __repr__(self) -> str:
        return (f"Map({str(self.root)!r}, places={len(self.places)}, layers={self.layers}, "
                f"map_id={self.map_id!r}, generation={self.generation})")

    def __len__(self) -> int:
        return len(self.store)

    @property
    def places(self) -> dict:
        """``{index: PlaceMeta}`` in index order: pose ``T_world_place``, neighbours, signatures, file."""
        return self.store.places

    @property
    def layers(self) -> list[str]:
        """The layers the map holds (:data:`scenesig.mapping.layers.LAYERS` order)."""
        from scenesig.mapping.layers import store_layers

        return store_layers(self.store)

    @property
    def map_id(self) -> str:
        return self.store.map_id

    @property
    def generation(self) -> int:
        return self.store.generation

    @property
    def history(self) -> list[dict]:
        """One entry per lifelong update (generation, runs, places updated)."""
        return self.store.history

    @property
    def identity(self) -> tuple[str, int]:
        """``(map_id, generation)``: one state of one map (what a localisation records of its map)."""
        return self.store.map_id, self.store.generation

    @property
    def settings(self) -> dict:
        """Every build setting, resolved, as the build used it (the manifest's ``params.settings``; for a
        map written before settings were recorded, its build overrides ``params.config``)."""
        params = self.store.params
        return params.get("settings") or params.get("config") or {}

    @property
    def camera(self):
        """The reference camera (:class:`scenesig.surveys.geometry.Camera`)."""
        return self.store.camera

    @property
    def summary(self):
        """``build_summary.json``, typed (:class:`scenesig.mapping.build_summary.BuildSummary`); None for a
        map without one (assembled by other means than build-map)."""
        from scenesig.mapping.build_summary import BuildSummary

        if self._summary is None and (self.root / "build_summary.json").is_file():
            self._summary = BuildSummary.read(self.root)
        return self._summary

    def load_place(self, index: int):
        """Place ``index``'s data (:class:`scenesig.mapping.codec.PlaceData`), checksum-verified."""
        return self.store.load_place(index)

    def nearest_place(self, T_world_vehicle) -> int:
        """The place nearest a world pose (position, then heading within 90 degrees)."""
        return self.store.nearest_place(T_world_vehicle)

    def refresh(self) -> bool:
        """Re-read the manifest after a lifelong update; True if the generation changed."""
        return self.store.refresh()
