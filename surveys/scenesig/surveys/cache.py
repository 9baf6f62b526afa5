"""The one small least-recently-used cache of the project (decoded map places, banks, point maps).

:class:`LRUCache` is a thread-safe mapping of at most ``size`` entries; a lookup moves its entry to
the most recent end and an insertion drops the least recently used ones beyond ``size``.  The map
store (:mod:`scenesig.mapping.store`), the scene-signature detector (:mod:`scenesig.localiser.detector`) and the
point-feature method (:mod:`scenesig.localiser.pointmethod`) keep their decoded places in one each.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Hashable

__all__ = ["LRUCache"]

_MISSING = object()


class LRUCache:
    """A bounded, thread-safe least-recently-used mapping.

    Parameters
    ----------
    size : the most entries kept; 0 keeps none (every :meth:`put` is dropped).

    Attributes
    ----------
    hits, misses : lookups by :meth:`get` that found / did not find their key.
    """

    def __init__(self, size: int):
        self.size = max(0, int(size))
        self._data: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, key: Hashable, default: Any = None) -> Any:
        """The value of ``key`` (now the most recently used), or ``default``; counts a hit or a miss."""
        with self._lock:
            value = self._data.get(key, _MISSING)
            if value is _MISSING:
                self.misses += 1
                return default
            self.hits += 1
            self._data.move_to_end(key)
            return value

    def put(self, key: Hashable, value: Any) -> None:
        """Store ``value`` as the most recently used entry, dropping the oldest beyond ``size``."""
        with self._lock:
            if not self.size:
                return
            self._data[key] = value
            self._data.move_to_end(key)
            while len(self._data) > self.size:
                self._data.popitem(last=False)

    def discard(self, key: Hashable) -> None:
        """Drop ``key`` if present."""
        with self._lock:
            self._data.pop(key, None)

    def keys(self) -> list:
        """The cached keys, least recently used first (a copy)."""
        with self._lock:
            return list(self._data)

    def clear(self) -> None:
        with self._lock:
            self._data.clear()

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._data

    def __len__(self) -> int:
        with self._lock:
            return len(self._data)
