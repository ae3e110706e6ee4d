"""Measurement repository: the append-only chained insert, filtered keyset paging, chain check.

Two ways to append: :meth:`MeasurementRepository.insert` seals a record against the head it reads
from the database; :meth:`MeasurementRepository.insert_links` writes links sealed beforehand (by
the station's journal, server/store/writer.py) exactly as they are, idempotently.
"""

from __future__ import annotations

import base64
import binascii
import json
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, cast

from sqlalchemy import Connection, Engine, Select, Table, func, insert, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import IntegrityError

from server.errors import ConflictError, InvalidInputError, NotFoundError
from server.store.bodies import envelope, residuals_of, stored_of, summary_of
from server.store.chain import GENESIS, canonical_json, seal
from server.store.models import MeasurementRow, OutboxRow
from server.store.schemas import (
    MAX_ID,
    ChainReport,
    MeasurementFilter,
    MeasurementRecord,
    MeasurementSummary,
    RecordResiduals,
    StoredMeasurement,
)

M = cast(Table, MeasurementRow.__table__)
_INDEXED = ("trigger_id", "part_id", "recipe", "recipe_version", "result", "reason_code", "reason")
# One statement object for every append: SQLAlchemy compiles it once (building it per record cost
# ~0.25 ms of the trigger's store time).
_INSERT = insert(M).returning(M.c.id)
# A sealed link written as it is: a (station, seq) already there is left alone (and compared).
_INSERT_LINK = {
    "postgresql": postgresql.insert(M)
    .on_conflict_do_nothing(index_elements=["station", "seq"])
    .returning(M.c.id),
    "sqlite": sqlite.insert(M)
    .on_conflict_do_nothing(index_elements=["station", "seq"])
    .returning(M.c.id),
}
_INSERT_OUTBOX = insert(cast(Table, OutboxRow.__table__))
# The outbox rows (server/store/outbox.py) of a link just inserted, given its database id.
OutboxRows = Callable[["Link", int], list[dict[str, Any]]]


class ChainConflictError(ConflictError):
    """The database holds a different chain than the one being written (another writer, a
    database restored from an older backup, a journal from another installation)."""


@dataclass(frozen=True)
class Link:
    """One sealed link of a station's chain: ``body`` is the exact text ``hash`` seals."""

    station: str
    seq: int
    prev_hash: str
    hash: str
    stored_at: datetime
    body: str
    record: MeasurementRecord

    def row(self) -> dict[str, Any]:
        """The measurements row of this link (the indexed columns come from the record)."""
        return {
            "station": self.station,
            "seq": self.seq,
            "stored_at": self.stored_at,
            "triggered_at": self.record.triggered_at,
            "body": self.body,
            "prev_hash": self.prev_hash,
            "hash": self.hash,
            **{k: getattr(self.record, k) for k in _INDEXED},
        }


def normalized(record: MeasurementRecord) -> MeasurementRecord:
    """The record as the chain stores it: ``triggered_at`` in UTC."""
    return record.model_copy(update={"triggered_at": record.triggered_at.astimezone(UTC)})


def seal_link(
    station: str,
    seq: int,
    prev_hash: str,
    stored_at: datetime,
    record: MeasurementRecord,
    record_json: dict[str, Any] | None = None,
) -> Link:
    """Seal ``record`` (already :func:`normalized`) as link ``seq`` after ``prev_hash``: the one
    definition of the body and its hash, used by both ways of appending."""
    body = canonical_json(
        {
            "station": station,
            "seq": seq,
            "stored_at": stored_at.isoformat(),
            "record": record_json if record_json is not None else record.model_dump(mode="json"),
        }
    )
    return Link(station, seq, prev_hash, seal(prev_hash, body), stored_at, body, record)


def link_from_body(prev_hash: str, hash_: str, body: str) -> Link:
    """A link read back from its stored text; refuses a body that does not hash to ``hash_``."""
    if seal(prev_hash, body) != hash_:
        raise ValueError(f"body does not hash to {hash_[:12]}… after {prev_hash[:12]}…")
    env = envelope(body)
    return Link(env.station, env.seq, prev_hash, hash_, env.stored_at, body, env.record)


def encode_cursor(last_id: int) -> str:
    return base64.urlsafe_b64encode(f"m:{last_id}".encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> int:
    """The id a page continues below; an unreadable cursor is the client's error, not ours."""
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
        tag, value = raw.split(":", 1)
        last_id = int(value)
        if tag != "m" or not 1 <= last_id <= MAX_ID:
            raise ValueError(raw)
    except (ValueError, UnicodeDecodeError, binascii.Error):
        raise InvalidInputError(
            f"cursor {cursor[:80]!r} is not a cursor this API returned"
        ) from None
    return last_id


class MeasurementRepository:
    """Every query on the measurements table of one station."""

    def __init__(self, engine: Engine, station: str, outbox: OutboxRows | None = None) -> None:
        self._engine = engine
        self.station = station
        # insert_links writes these rows in the transaction of each link it inserts
        self.outbox = outbox
        # One writer per process: seq and prev_hash are read and written in one transaction, and
        # the unique (station, seq) constraint catches a second process writing the same chain.
        self._write_lock = threading.Lock()
        # The chain's head (seq, hash) as this writer left it, so an append needs no query for
        # it. Another writer appending meanwhile makes ours collide on (station, seq): the head
        # is then read again from the database and the append retried.
        self._head: tuple[int, str] | None = None

    # ------------------------------------------------------------------ writing
    def insert(self, record: MeasurementRecord) -> StoredMeasurement:
        """Append a record to the chain and commit it durably; returns it with seq and hash."""
        if record.station != self.station:
            raise InvalidInputError(
                f"record of station {record.station!r} given to the store of {self.station!r}"
            )
        record = normalized(record)
        record_json = record.model_dump(mode="json")
        for attempt in range(3):
            try:
                with self._write_lock:
                    return self._append(record, record_json)
            except IntegrityError as err:
                if attempt == 2:
                    raise ConflictError(
                        f"station {self.station!r}: another writer extends the same chain "
                        f"({err.orig})"
                    ) from err
        raise AssertionError("unreachable")

    def _append(self, record: MeasurementRecord, record_json: dict[str, Any]) -> StoredMeasurement:
        stored_at = datetime.now(UTC)
        try:
            new_id, seq, prev, digest = self._write(record, record_json, stored_at)
        except BaseException:
            self._head = None  # whatever failed, the next append reads the head again
            raise
        self._head = (seq, digest)  # committed
        return StoredMeasurement(
            id=new_id, seq=seq, stored_at=stored_at, prev_hash=prev, hash=digest, record=record
        )

    def _write(
        self, record: MeasurementRecord, record_json: dict[str, Any], stored_at: datetime
    ) -> tuple[int, int, str, str]:
        """One append in one transaction: (id, seq, prev_hash, hash) once it is committed."""
        with self._engine.begin() as conn:
            if self._head is None:
                last = conn.execute(
                    select(M.c.seq, M.c.hash)
                    .where(M.c.station == self.station)
                    .order_by(M.c.seq.desc())
                    .limit(1)
                ).first()
                self._head = (last.seq, last.hash) if last else (0, GENESIS)
            seq, prev = self._head[0] + 1, self._head[1]
            link = seal_link(self.station, seq, prev, stored_at, record, record_json)
            new_id = conn.execute(_INSERT, link.row()).scalar_one()
            digest = link.hash
        return new_id, seq, prev, digest

    def insert_links(self, links: Sequence[Link]) -> list[int]:
        """Write consecutive sealed links in one transaction, exactly as sealed; their ids.

        Idempotent: a link whose (station, seq) is stored with the same hash is a no-op (its id
        is returned), with another hash a :class:`ChainConflictError`. The first link must follow
        the stored chain: its predecessor is stored with hash ``prev_hash`` (or it is seq 1).
        With ``outbox``, each link inserted gets its outbox rows in the same transaction.
        """
        if not links:
            return []
        for a, b in zip(links, links[1:], strict=False):
            if b.seq != a.seq + 1 or b.prev_hash != a.hash:
                raise ValueError(f"links seq {a.seq} and {b.seq} are not consecutive links")
        for link in links:
            if link.station != self.station:
                raise InvalidInputError(
                    f"link of station {link.station!r} given to the store of {self.station!r}"
                )
        with self._engine.begin() as conn:
            self._check_predecessor(conn, links[0])
            statement = _INSERT_LINK[conn.dialect.name]
            ids = []
            for link in links:
                new_id = conn.execute(statement, link.row()).scalar_one_or_none()
                if new_id is not None and self.outbox is not None:
                    rows = self.outbox(link, new_id)
                    if rows:
                        conn.execute(_INSERT_OUTBOX, rows)
                ids.append(new_id if new_id is not None else self._existing(conn, link))
        return ids

    def _check_predecessor(self, conn: Connection, link: Link) -> None:
        if link.seq == 1:
            if link.prev_hash != GENESIS:
                raise ChainConflictError(
                    f"station {self.station!r}: seq 1 must follow the genesis hash, "
                    f"not {link.prev_hash[:12]}…"
                )
            return
        prev = conn.execute(
            select(M.c.hash).where(M.c.station == self.station, M.c.seq == link.seq - 1)
        ).scalar_one_or_none()
        if prev is None:
            raise ChainConflictError(
                f"station {self.station!r}: seq {link.seq - 1} is not in the database, so seq "
                f"{link.seq} cannot follow it (a database restored from an older backup, or "
                f"another database than the journal's?)"
            )
        if prev != link.prev_hash:
            raise ChainConflictError(
                f"station {self.station!r}: the database's seq {link.seq - 1} has hash "
                f"{prev[:12]}…, the journal's seq {link.seq} follows {link.prev_hash[:12]}… "
                f"(another writer extends this chain?)"
            )

    def _existing(self, conn: Connection, link: Link) -> int:
        row = conn.execute(
            select(M.c.id, M.c.hash).where(M.c.station == self.station, M.c.seq == link.seq)
        ).first()
        if row is None:  # the conflict was not on (station, seq): only a hash can collide
            raise ChainConflictError(
                f"station {self.station!r}: seq {link.seq} was refused although no record has "
                f"that seq (hash {link.hash[:12]}… is stored under another seq or station)"
            )
        if row.hash != link.hash:
            raise ChainConflictError(
                f"station {self.station!r}: seq {link.seq} is stored with hash {row.hash[:12]}… "
                f"but this writer sealed it as {link.hash[:12]}… (two writers on one chain?)"
            )
        return int(row.id)

    def head(self) -> tuple[int, str]:
        """(seq, hash) of the newest stored link; (0, genesis) for an empty chain."""
        with self._engine.connect() as conn:
            last = conn.execute(
                select(M.c.seq, M.c.hash)
                .where(M.c.station == self.station)
                .order_by(M.c.seq.desc())
                .limit(1)
            ).first()
        return (int(last.seq), str(last.hash)) if last else (0, GENESIS)

    def hash_at(self, seq: int) -> str | None:
        """The stored hash of link ``seq``, None when it is not stored."""
        with self._engine.connect() as conn:
            found = conn.execute(
                select(M.c.hash).where(M.c.station == self.station, M.c.seq == seq)
            ).scalar_one_or_none()
        return None if found is None else str(found)

    # ------------------------------------------------------------------ reading
    def get(self, measurement_id: int) -> StoredMeasurement:
        with self._engine.connect() as conn:
            row = conn.execute(
                select(M).where(M.c.station == self.station, M.c.id == measurement_id)
            ).first()
        if row is None:
            raise NotFoundError(
                f"measurement {measurement_id} does not exist at station {self.station!r}"
            )
        return stored_of(row)

    def page(
        self, filters: MeasurementFilter, cursor: str | None, limit: int
    ) -> tuple[list[StoredMeasurement], str | None]:
        """Newest first; ``next_cursor`` is None on the last page (keyset paging on id)."""
        rows, next_cursor = self._keyset(filters, cursor, limit)
        return [stored_of(r) for r in rows], next_cursor

    def summary_page(
        self, filters: MeasurementFilter, cursor: str | None, limit: int
    ) -> tuple[list[MeasurementSummary], str | None]:
        """As :meth:`page`, without detections: about 3x cheaper to read (REST lists)."""
        rows, next_cursor = self._keyset(filters, cursor, limit)
        return [summary_of(r) for r in rows], next_cursor

    def _keyset(
        self, filters: MeasurementFilter, cursor: str | None, limit: int
    ) -> tuple[list[Any], str | None]:
        """Up to ``limit`` rows newest first, and the cursor of the next page (None if last)."""
        query = self._filtered(filters).order_by(M.c.id.desc()).limit(limit + 1)
        if cursor is not None:
            query = query.where(M.c.id < decode_cursor(cursor))
        with self._engine.connect() as conn:
            rows = conn.execute(query).all()
        items = list(rows[:limit])
        more = len(rows) > limit
        return items, (encode_cursor(items[-1].id) if more and items else None)

    def residuals_after(self, after_id: int, limit: int) -> list[RecordResiduals]:
        """The per-camera residuals of the newest ``limit`` records with an id above
        ``after_id``, oldest first: the drift watch's read. Only the fields it needs are built
        from each body (about a fifth of parsing the whole record); a record without residuals
        comes with an empty list, so the reader still moves past it."""
        query = (select(M.c.id, M.c.body).where(M.c.station == self.station, M.c.id > after_id)
                 .order_by(M.c.id.desc()).limit(limit))
        with self._engine.connect() as conn:
            rows = conn.execute(query).all()
        return [residuals_of(r) for r in reversed(rows)]

    def iterate(self, filters: MeasurementFilter, batch: int = 500) -> Iterator[StoredMeasurement]:
        """Every matching record, oldest first, fetched in batches (for exports)."""
        for rows in self._batches(filters, batch):
            yield from (stored_of(r) for r in rows)

    def iterate_summaries(
        self, filters: MeasurementFilter, batch: int = 500
    ) -> Iterator[MeasurementSummary]:
        """Every matching record's summary, oldest first (CSV export)."""
        for rows in self._batches(filters, batch):
            yield from (summary_of(r) for r in rows)

    def _batches(self, filters: MeasurementFilter, batch: int) -> Iterator[list[Any]]:
        # Keyset batches, each on its own short-lived connection: a slow export client never
        # holds a read transaction open (which would stop SQLite's WAL checkpoints).
        last_id = 0
        while True:
            query = self._filtered(filters).where(M.c.id > last_id).order_by(M.c.id).limit(batch)
            with self._engine.connect() as conn:
                rows = list(conn.execute(query).all())
            if rows:
                yield rows
            if len(rows) < batch:
                return
            last_id = rows[-1].id

    def summaries_from(self, filters: MeasurementFilter, start: int,
                       limit: int) -> tuple[int, Iterator[MeasurementSummary]]:
        """How many records match, and the summaries of ``limit`` of them from the ``start``-th,
        oldest first (decoded as they are taken): paging by index, as OPC UA's
        GetResultListFiltered does, keeps its meaning while new records arrive at the end."""
        query = self._filtered(filters)
        page = query.order_by(M.c.seq).offset(max(start, 0)).limit(max(limit, 0))
        with self._engine.connect() as conn:
            total = int(conn.execute(query.with_only_columns(func.count())).scalar_one())
            rows = list(conn.execute(page).all()) if limit > 0 else []
        return total, (summary_of(r) for r in rows)

    def count(self, filters: MeasurementFilter | None = None) -> int:
        query = self._filtered(filters or MeasurementFilter()).with_only_columns(func.count())
        with self._engine.connect() as conn:
            return int(conn.execute(query).scalar_one())

    def _filtered(self, f: MeasurementFilter) -> Select[Any]:
        q = select(M).where(M.c.station == self.station)
        if f.since is not None:
            q = q.where(M.c.triggered_at >= _aware(f.since, "since"))
        if f.until is not None:
            q = q.where(M.c.triggered_at < _aware(f.until, "until"))
        if f.result is not None:
            q = q.where(M.c.result == f.result)
        if f.reason_code is not None:
            q = q.where(M.c.reason_code == f.reason_code)
        if f.recipe is not None:
            q = q.where(M.c.recipe == f.recipe)
        if f.part_id is not None:
            q = q.where(M.c.part_id == f.part_id)
        if f.result_id is not None:
            q = q.where(M.c.seq == f.result_id)
        if f.trigger_id is not None:
            q = q.where(M.c.trigger_id == f.trigger_id)
        return q

    # ------------------------------------------------------------------ audit
    def verify_chain(self, batch: int = 1000) -> ChainReport:
        """Recompute every link: seq continuity, prev_hash, hash of the body, columns = body."""
        prev, expected_seq, checked = GENESIS, 1, 0
        while True:
            with self._engine.connect() as conn:
                rows = conn.execute(
                    select(M)
                    .where(M.c.station == self.station, M.c.seq >= expected_seq)
                    .order_by(M.c.seq)
                    .limit(batch)
                ).all()
            for r in rows:
                problem = _link_problem(r, prev, expected_seq, self.station)
                if problem:
                    return ChainReport(
                        ok=False,
                        station=self.station,
                        checked=checked,
                        head_seq=expected_seq - 1 if checked else None,
                        head_hash=prev if checked else None,
                        first_bad_seq=r.seq,
                        problem=problem,
                    )
                prev, expected_seq, checked = r.hash, r.seq + 1, checked + 1
            if len(rows) < batch:
                break
        return ChainReport(
            ok=True,
            station=self.station,
            checked=checked,
            head_seq=expected_seq - 1 if checked else None,
            head_hash=prev if checked else None,
        )


def _link_problem(r: Any, prev: str, expected_seq: int, station: str) -> str | None:
    if r.seq != expected_seq:
        return f"seq {expected_seq} is missing (next stored is {r.seq})"
    if r.prev_hash != prev:
        return (
            f"seq {r.seq}: prev_hash {r.prev_hash[:12]}… does not match "
            f"hash {prev[:12]}… of seq {r.seq - 1}"
        )
    if seal(r.prev_hash, r.body) != r.hash:
        return f"seq {r.seq}: body does not hash to the stored hash {r.hash[:12]}…"
    try:
        env = json.loads(r.body)
        record = MeasurementRecord.model_validate(env["record"])
    except (ValueError, KeyError) as err:
        return f"seq {r.seq}: body is not a valid record ({str(err).splitlines()[0]})"
    if env.get("station") != station or env.get("seq") != r.seq:
        return f"seq {r.seq}: body names station {env.get('station')!r} seq {env.get('seq')!r}"
    for key in _INDEXED:
        if getattr(record, key) != getattr(r, key):
            return (
                f"seq {r.seq}: column {key} = {getattr(r, key)!r} "
                f"but the record says {getattr(record, key)!r}"
            )
    if datetime.fromisoformat(env.get("stored_at", "")) != r.stored_at:
        return (
            f"seq {r.seq}: column stored_at = {r.stored_at} "
            f"but the body says {env.get('stored_at')}"
        )
    if record.triggered_at != r.triggered_at:
        return (
            f"seq {r.seq}: column triggered_at = {r.triggered_at} "
            f"but the record says {record.triggered_at}"
        )
    return None


def _aware(t: datetime, name: str) -> datetime:
    if t.tzinfo is None:
        raise InvalidInputError(f"{name} = {t.isoformat()} has no time zone; add Z or +hh:mm")
    return t
