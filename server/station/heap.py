"""The station's start-up heap is kept out of Python's cyclic garbage collector.

CPython's collector runs its oldest generation when the objects that survived the younger ones
reach a quarter of those already there, and then traverses every tracked object of the process
while holding the GIL. A started station holds about 260,000 (its recipes and their cached
window predictions, NumPy, OpenCV, SQLAlchemy, the links' libraries): one such collection took
136-140 ms on station 1, once within the first 1,000 triggers after start-up, and the trigger it
fell on took 146-151 ms (`python -m bench.gc_pause`): a stall no deadline survives. Those
objects live as long as the station, so :func:`freeze` moves them, once everything is loaded and
warmed up, to the collector's permanent generation (``gc.freeze``): later collections traverse
only what came after. Objects still free by reference counting as before; only cycles among the
frozen ones are never collected, and a station makes its cycles (the recipes' caches) before it
is ready. :func:`thaw` gives them back when the station stops (a process that starts stations
one after another, as the tests do).
"""

from __future__ import annotations

import gc
import logging

log = logging.getLogger(__name__)


def freeze() -> int:
    """Collect what is garbage now, then keep every object alive out of later collections;
    returns how many objects were frozen."""
    gc.collect()
    gc.freeze()
    count = gc.get_freeze_count()
    log.info("start-up heap: %d objects kept out of the garbage collector", count)
    return count


def thaw() -> None:
    """Give the frozen objects back to the collector."""
    gc.unfreeze()
