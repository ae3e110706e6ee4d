"""A small thread-safe LRU for values derived from frozen objects, keyed by their identity.

A station works with the same camera, recipe and layout objects trigger after trigger, and the
work derived from them (packed camera arrays, window predictions, ...) need not be redone. An
entry is found by the ids of its ``owners`` plus a plain hashable ``extra`` key, and used only
while those very objects are what the caller passes (it holds them, so an id cannot be reused
by another object while the entry lives). Frozen owners are the caller's contract: a changed
station or recipe is a new object and never meets a stale value.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from threading import Lock
from typing import Generic, TypeVar

V = TypeVar("V")


class IdentityCache(Generic[V]):
    """At most ``size`` values, least recently used dropped first."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"an IdentityCache needs size >= 1, got {size}")
        self.size = size
        self._entries: OrderedDict[Hashable, tuple[tuple[object, ...], V]] = OrderedDict()
        self._lock = Lock()

    def get(self, owners: tuple[object, ...], extra: Hashable, make: Callable[[], V]) -> V:
        """The value for (``owners``, ``extra``); ``make()`` computes it when there is none.

        ``make`` runs outside the lock; an exception from it leaves the cache unchanged.
        """
        key, hit = self._find(owners, extra)
        if hit is not None:
            return hit[0]
        value = make()
        with self._lock:
            self._entries[key] = (owners, value)
            self._entries.move_to_end(key)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)
        return value

    def peek(self, owners: tuple[object, ...], extra: Hashable) -> V | None:
        """The value for (``owners``, ``extra``) if there is one (then the most recently used),
        else None; nothing is computed."""
        hit = self._find(owners, extra)[1]
        return None if hit is None else hit[0]

    def _find(self, owners: tuple[object, ...],
              extra: Hashable) -> tuple[Hashable, tuple[V] | None]:
        """The entry's key, and its value (in a 1-tuple, then the most recently used) when it
        is there for these very owners."""
        key = (tuple(id(o) for o in owners), extra)
        with self._lock:
            hit = self._entries.get(key)
            if hit is not None and all(a is b for a, b in zip(hit[0], owners, strict=True)):
                self._entries.move_to_end(key)
                return key, (hit[1],)
        return key, None

    def values(self) -> list[V]:
        """The values held, least recently used first."""
        with self._lock:
            return [v for _, v in self._entries.values()]

    def __len__(self) -> int:
        return len(self._entries)
