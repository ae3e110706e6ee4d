"""SQLAlchemy 2 tables of the store; the Alembic migrations in ./migrations create exactly these."""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import (
    BigInteger,
    Boolean,
    DateTime,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator


class UTCDateTime(TypeDecorator[datetime]):
    """Aware UTC datetimes in and out; SQLite keeps naive text, so normalise before comparing."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value.isoformat()} given to the store; use UTC")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    pass


class MeasurementRow(Base):
    """One trigger's record. Append-only (database triggers refuse UPDATE and DELETE)."""

    __tablename__ = "measurements"
    __table_args__ = (
        UniqueConstraint("station", "seq", name="uq_measurements_station_seq"),
        Index("ix_measurements_station_time", "station", "triggered_at"),
        Index("ix_measurements_station_part", "station", "part_id"),
        Index("ix_measurements_station_id", "station", "id"),  # newest-first paging
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    station: Mapped[str] = mapped_column(String(64))
    seq: Mapped[int] = mapped_column(BigInteger)
    stored_at: Mapped[datetime] = mapped_column(UTCDateTime())
    triggered_at: Mapped[datetime] = mapped_column(UTCDateTime())
    trigger_id: Mapped[int] = mapped_column(BigInteger)
    part_id: Mapped[str | None] = mapped_column(String(64))
    recipe: Mapped[str] = mapped_column(String(64))
    recipe_version: Mapped[int] = mapped_column(Integer)
    result: Mapped[str] = mapped_column(String(3))
    reason_code: Mapped[int] = mapped_column(Integer)
    reason: Mapped[str] = mapped_column(String(64))
    # The canonical JSON envelope exactly as hashed: Text, not JSONB, which would re-format it.
    body: Mapped[str] = mapped_column(Text)
    prev_hash: Mapped[str] = mapped_column(String(64))
    hash: Mapped[str] = mapped_column(String(64), unique=True)


class ImageRow(Base):
    """An archived frame; mutable (eviction), unlike the measurement that references it."""

    __tablename__ = "images"
    __table_args__ = (Index("ix_images_evict", "evicted_at", "ok", "id"),)

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    measurement_id: Mapped[int] = mapped_column(ForeignKey("measurements.id"), index=True)
    view: Mapped[int] = mapped_column(Integer)
    camera_id: Mapped[str] = mapped_column(String(64))
    path: Mapped[str] = mapped_column(String(400), unique=True)
    bytes: Mapped[int] = mapped_column(BigInteger)
    ok: Mapped[bool] = mapped_column(Boolean)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime())
    evicted_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class VersionRow(Base):
    """One version of a recipe or a calibration; content is canonical JSON, sha256 its hash."""

    __tablename__ = "config_versions"
    __table_args__ = (
        UniqueConstraint("station", "kind", "name", "version", name="uq_config_versions"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    station: Mapped[str] = mapped_column(String(64))
    kind: Mapped[str] = mapped_column(String(16))
    name: Mapped[str] = mapped_column(String(64))
    version: Mapped[int] = mapped_column(Integer)
    content: Mapped[str] = mapped_column(Text)
    sha256: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime())
    created_by: Mapped[str] = mapped_column(String(64))
    comment: Mapped[str] = mapped_column(String(400))


class ActiveVersionRow(Base):
    """Which version of each recipe / calibration the station uses now."""

    __tablename__ = "active_versions"

    station: Mapped[str] = mapped_column(String(64), primary_key=True)
    kind: Mapped[str] = mapped_column(String(16), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    version_id: Mapped[int] = mapped_column(ForeignKey("config_versions.id"))
    activated_at: Mapped[datetime] = mapped_column(UTCDateTime())
    activated_by: Mapped[str] = mapped_column(String(64))


class TokenRow(Base):
    """An API token, stored only as the sha256 of its secret."""

    __tablename__ = "tokens"

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    role: Mapped[str] = mapped_column(String(16))
    token_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime())
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class OutboxRow(Base):
    """One message to publish (MQTT), written in the transaction that inserts its measurement;
    ``published_at`` is set once the broker acknowledged it (PUBACK). Not append-only: published
    rows are deleted after the station's ``plant.mqtt.keep_published_h``."""

    __tablename__ = "outbox"
    __table_args__ = (
        UniqueConstraint("station", "seq", "topic", name="uq_outbox_station_seq_topic"),
        Index("ix_outbox_station_pending", "station", "published_at", "id"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    station: Mapped[str] = mapped_column(String(64))
    seq: Mapped[int] = mapped_column(BigInteger)  # the record's result id
    measurement_id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"))
    topic: Mapped[str] = mapped_column(String(400))
    payload: Mapped[str] = mapped_column(Text)  # JSON
    created_at: Mapped[datetime] = mapped_column(UTCDateTime())
    published_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class GaugeStudyRow(Base):
    """One gauge study (docs/gauge.md): its canonical JSON body, chained by sha256 to the
    station's previous study as measurements are. Append-only (database triggers)."""

    __tablename__ = "gauge_studies"
    __table_args__ = (UniqueConstraint("station", "seq", name="uq_gauge_studies_station_seq"),)

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    station: Mapped[str] = mapped_column(String(64))
    seq: Mapped[int] = mapped_column(BigInteger)
    kind: Mapped[str] = mapped_column(String(16))
    recipe: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime())
    created_by: Mapped[str] = mapped_column(String(64))
    passed: Mapped[bool] = mapped_column(Boolean)
    body: Mapped[str] = mapped_column(Text)
    prev_hash: Mapped[str] = mapped_column(String(64))
    hash: Mapped[str] = mapped_column(String(64), unique=True)


class UserRow(Base):
    """A person who logs in on the operator page with a PIN or a password (server/users.py);
    the secret is stored only as its scrypt hash with the user's own salt."""

    __tablename__ = "users"

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    role: Mapped[str] = mapped_column(String(16))
    secret_kind: Mapped[str] = mapped_column(String(8))  # "pin" or "password"
    secret_hash: Mapped[str] = mapped_column(String(200))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime())
    disabled_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    failed_count: Mapped[int] = mapped_column(Integer)  # wrong secrets since the last login
    last_failed_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    locked_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    # Bumped by a reset or a disable: a page session opened before it is over.
    epoch: Mapped[int] = mapped_column(Integer)


class UserEventRow(Base):
    """The users' audit trail: logins, wrong secrets, lockouts and every change an engineer
    made. Append-only (database triggers)."""

    __tablename__ = "user_events"
    __table_args__ = (Index("ix_user_events_user", "user_name", "id"),)

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime())
    station: Mapped[str] = mapped_column(String(64))
    user_name: Mapped[str] = mapped_column(String(64))
    event: Mapped[str] = mapped_column(String(16))
    actor: Mapped[str] = mapped_column(String(64))  # who did it: the user, an engineer, "cli"
    detail: Mapped[str] = mapped_column(Text)


class AlarmRow(Base):
    """One alarm (docs/alarms.md): raised by a source, cleared when its condition ends,
    acknowledged by an operator. At most one active row per (station, source, code): the
    partial unique index makes raising idempotent. Its history is in ``alarm_events``."""

    __tablename__ = "alarms"
    __table_args__ = (
        Index("uq_alarms_active", "station", "source", "code", unique=True,
              sqlite_where=text("cleared_at IS NULL"),
              postgresql_where=text("cleared_at IS NULL")),
        Index("ix_alarms_station_raised", "station", "raised_at"),
    )

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    station: Mapped[str] = mapped_column(String(64))
    source: Mapped[str] = mapped_column(String(64))
    code: Mapped[str] = mapped_column(String(32))
    priority: Mapped[str] = mapped_column(String(8))
    text: Mapped[str] = mapped_column(String(400))
    text_key: Mapped[str] = mapped_column(String(64))
    text_args: Mapped[str] = mapped_column(Text)  # JSON object
    raised_at: Mapped[datetime] = mapped_column(UTCDateTime())
    cleared_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    acked_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    acked_by: Mapped[str | None] = mapped_column(String(64))


class AlarmEventRow(Base):
    """One transition of an alarm (raised, acknowledged, cleared), by whom: the alarms' audit
    trail. Append-only (database triggers); its id is the MQTT message's ``seq``."""

    __tablename__ = "alarm_events"
    __table_args__ = (Index("ix_alarm_events_alarm", "alarm_id"),)

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True)
    station: Mapped[str] = mapped_column(String(64))
    alarm_id: Mapped[int] = mapped_column(ForeignKey("alarms.id"))
    at: Mapped[datetime] = mapped_column(UTCDateTime())
    kind: Mapped[str] = mapped_column(String(16))
    by: Mapped[str | None] = mapped_column(String(64))
