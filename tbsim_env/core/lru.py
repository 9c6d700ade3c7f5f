"""``LRU``: a bounded mapping that drops its least recently used entry first: the one rule
behind tbsim's caches of built things (road-edge grids, IDM lane graphs and scene plans,
training-cache shards)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Generic, TypeVar

K = TypeVar("K")
V = TypeVar("V")


class LRU(Generic[K, V]):
    """At most ``size`` entries (None: no bound); ``get`` and ``put`` mark an entry as the most
    recently used, ``put`` drops the least recently used ones beyond ``size``."""

    def __init__(self, size: int | None) -> None:
        self.size = size
        self._items: OrderedDict[K, V] = OrderedDict()

    def get(self, key: K) -> V | None:
        """The value kept for ``key``, or None."""
        value = self._items.get(key)
        if value is not None:
            self._items.move_to_end(key)
        return value

    def put(self, key: K, value: V) -> V:
        """Keep ``value`` for ``key``; returns it."""
        self._items[key] = value
        self._items.move_to_end(key)
        while self.size is not None and len(self._items) > self.size:
            self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        self._items.clear()

    def __len__(self) -> int:
        return len(self._items)


__all__ = ["LRU"]
