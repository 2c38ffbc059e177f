"""A least-recently-used cache bounded in bytes, shared by the diagnosis's caches (field
runs, a worker's binned points, a surface sampler's nearest samples)."""

from __future__ import annotations

from collections import OrderedDict

__all__ = ["LruCache"]


class LruCache(OrderedDict):
    """Values by key, least recently used first, at most ``limit`` bytes as ``size(value)``
    counts them and at most ``max_items`` values (the most recent always stays). Holds the
    diagnosis's field runs and a worker's binned points: a value dropped and asked for
    again is computed again, and both are deterministic, so answers do not depend on the
    limits, only the work does."""

    def __init__(self, limit: int, size, max_items: int | None = None):
        super().__init__()
        self.limit, self.size, self.max_items, self.bytes = int(limit), size, max_items, 0
        self.dropped: set = set()
        """Keys the limits have evicted (a caller counts the work it repeats)."""

    def get_recent(self, key):
        """The value under ``key`` (marked recently used), or None."""
        value = super().get(key)
        if value is not None:
            self.move_to_end(key)
        return value

    def put(self, key, value) -> None:
        if key in self:
            self.bytes -= self.size(self.pop(key))
        self[key] = value
        self.bytes += self.size(value)
        while len(self) > 1 and (self.bytes > self.limit or (self.max_items is not None and len(self) > self.max_items)):
            key, old = self.popitem(last=False)
            self.bytes -= self.size(old)
            self.dropped.add(key)

    def clear(self) -> None:
        super().clear()
        self.bytes = 0
