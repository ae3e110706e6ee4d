"""The result store: one object holding the engine and a repository per table group, and the
station's durable writer of its audit chain (journal first, database behind it)."""

from __future__ import annotations

from sqlalchemy import Engine

from server.store.alarms import AlarmRepository
from server.store.archive import ImageRepository
from server.store.db import create_store_engine, current_revision, migrate, ping
from server.store.gauge import GaugeStudyRepository
from server.store.measurements import MeasurementRepository
from server.store.shifts import ShiftRepository
from server.store.tokens import TokenRepository
from server.store.users import UserRepository
from server.store.versions import VersionRepository
from server.store.writer import DurableWriter, Sealed, StoreFailedError, WriterStatus

__all__ = ["DurableWriter", "Sealed", "Store", "StoreFailedError", "WriterStatus", "open_store"]


class Store:
    """The station's database: ``measurements``, ``images``, ``versions``, ``tokens``,
    ``gauge`` (the gauge studies), ``users`` (the operator page's people), ``shifts`` (the
    line view's figures over ``measurements``) and ``alarms``.

    Every method is blocking (SQLAlchemy Core on a pooled connection): call it from a worker
    thread, never on the event loop (FastAPI runs ``def`` endpoints in its threadpool).
    """

    def __init__(self, engine: Engine, station: str) -> None:
        self.engine = engine
        self.station = station
        self.measurements = MeasurementRepository(engine, station)
        self.images = ImageRepository(engine, station)
        self.versions = VersionRepository(engine, station)
        self.shifts = ShiftRepository(engine, station)
        self.tokens = TokenRepository(engine)
        self.gauge = GaugeStudyRepository(engine, station)
        self.users = UserRepository(engine, station)
        self.alarms = AlarmRepository(engine, station)

    @property
    def dialect(self) -> str:
        return self.engine.dialect.name

    def ping(self) -> None:
        ping(self.engine)

    def revision(self) -> str | None:
        return current_revision(self.engine)

    def close(self) -> None:
        self.engine.dispose()


def open_store(url: str, station: str, sqlite_synchronous: str = "FULL") -> Store:
    """Open (and migrate to the newest schema) the store at ``url`` for ``station``."""
    engine = create_store_engine(url, sqlite_synchronous)
    try:
        migrate(engine)
    except Exception:
        engine.dispose()
        raise
    return Store(engine, station)
