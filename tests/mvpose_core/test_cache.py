"""The identity-keyed LRU behind the per-trigger caches (camera tables, layouts, predictions)."""

from __future__ import annotations

import pytest

from mvpose_core.cache import IdentityCache


class Owner:
    def __init__(self, name: str) -> None:
        self.name = name

    def __eq__(self, other: object) -> bool:  # equal by value: the cache must still tell apart
        return isinstance(other, Owner) and other.name == self.name

    def __hash__(self) -> int:
        return hash(self.name)


def test_hits_only_the_very_same_owners_and_extra_key() -> None:
    cache: IdentityCache[str] = IdentityCache(4)
    a, b = Owner("a"), Owner("b")
    calls: list[str] = []

    def make(v: str):  # type: ignore[no-untyped-def]
        return lambda: calls.append(v) or v

    assert cache.get((a, b), 1, make("first")) == "first"
    assert cache.get((a, b), 1, make("again")) == "first"  # hit
    assert cache.get((a, b), 2, make("other extra")) == "other extra"
    assert cache.get((Owner("a"), b), 1, make("equal, not same")) == "equal, not same"
    assert calls == ["first", "other extra", "equal, not same"]


def test_a_failing_make_leaves_nothing_and_the_size_is_bounded() -> None:
    cache: IdentityCache[int] = IdentityCache(2)
    owner = Owner("x")

    def boom() -> int:
        raise ValueError("refused")

    with pytest.raises(ValueError, match="refused"):
        cache.get((owner,), 0, boom)
    assert len(cache) == 0
    for k in range(5):
        cache.get((owner,), k, lambda k=k: k)  # type: ignore[misc]
    assert len(cache) == 2 and cache.values() == [3, 4]
    assert cache.get((owner,), 0, lambda: -1) == -1  # the oldest were dropped
    with pytest.raises(ValueError, match="size"):
        IdentityCache(0)


def test_peek_finds_without_making() -> None:
    cache: IdentityCache[str] = IdentityCache(2)
    a = Owner("a")
    assert cache.peek((a,), 1) is None and len(cache) == 0
    cache.get((a,), 1, lambda: "one")
    cache.get((a,), 2, lambda: "two")
    assert cache.peek((a,), 1) == "one"  # and now the most recently used
    assert cache.peek((Owner("a"),), 1) is None
    cache.get((a,), 3, lambda: "three")
    assert cache.values() == ["one", "three"]
