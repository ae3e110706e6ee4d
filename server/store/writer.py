"""The durable writer: seals each record locally, journals it, and lets a thread commit it.

The trigger thread calls :meth:`DurableWriter.append`. It seals the record as the next link of
the station's chain (seq = head + 1: the result id the PLC gets), appends it to the journal
(server/store/journal.py, fsynced), hands it to the database thread and waits for that commit
at most ``db_wait_s``. Whatever the database does (frozen, restarting, unreachable), an append
costs the journal write plus at most ``db_wait_s``; the database thread inserts the journalled
links strictly in seq order, retrying with backoff, and each link's database id arrives later
through :meth:`Sealed.wait_id` or :meth:`Sealed.on_committed`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, event
from sqlalchemy.engine import make_url

from server.errors import StoreUnavailableError
from server.store.chain import GENESIS
from server.store.db import create_store_engine, migrate
from server.store.journal import PREALLOCATE, Journal, journal_dir
from server.store.measurements import (
    ChainConflictError,
    Link,
    MeasurementRepository,
    OutboxRows,
    normalized,
    seal_link,
)
from server.store.schemas import MeasurementRecord, StoredMeasurement

log = logging.getLogger(__name__)

_BATCH = 100  # links per transaction when the database catches up after an outage


class StoreFailedError(Exception):
    """The journal could not take the record: nothing was sealed (the PLC gets STORE_FAILED)."""


class _Commit:
    """The database id of one link, once its insert has committed."""

    def __init__(self) -> None:
        self.id: int | None = None
        self._done = threading.Event()
        self._lock = threading.Lock()
        self._callbacks: list[Callable[[int], object]] = []

    def set(self, db_id: int) -> None:
        with self._lock:
            self.id = db_id
            callbacks, self._callbacks = self._callbacks, []
        self._done.set()
        for cb in callbacks:
            _call(cb, db_id)

    def wait(self, timeout: float | None) -> int | None:
        self._done.wait(timeout)
        return self.id

    def add(self, cb: Callable[[int], object]) -> None:
        with self._lock:
            if self.id is None:
                self._callbacks.append(cb)
                return
            db_id = self.id
        _call(cb, db_id)


def _call(cb: Callable[[int], object], db_id: int) -> None:
    try:
        cb(db_id)
    except Exception:
        log.exception("callback for measurement id %d failed", db_id)


@dataclass(frozen=True)
class Sealed:
    """A journalled record: its place in the chain now, its database id once committed."""

    link: Link
    _commit: _Commit = field(repr=False, compare=False)
    journal_ms: float = 0.0  # the journal write and its fsync, of the whole append

    @property
    def seq(self) -> int:
        """The result id: this record's seq in the station's chain."""
        return self.link.seq

    @property
    def prev_hash(self) -> str:
        return self.link.prev_hash

    @property
    def hash(self) -> str:
        return self.link.hash

    @property
    def stored_at(self) -> datetime:
        return self.link.stored_at

    @property
    def record(self) -> MeasurementRecord:
        return self.link.record

    @property
    def id(self) -> int | None:
        """The database id, or None while the insert has not committed."""
        return self._commit.id

    def wait_id(self, timeout: float | None = None) -> int | None:
        """The database id once committed, waiting up to ``timeout`` s (None: as long as it
        takes); None if it is not committed by then."""
        return self._commit.wait(timeout)

    def on_committed(self, callback: Callable[[int], object]) -> None:
        """Call ``callback(db_id)`` once committed: at once (in this thread) if it already is,
        else on the database thread, which it must not hold up (hand work to an executor)."""
        self._commit.add(callback)

    def stored(self) -> StoredMeasurement:
        """As the store returns it (needs the database id: call once committed)."""
        if self.id is None:
            raise RuntimeError(f"seq {self.seq} is not committed to the database yet")
        return StoredMeasurement(id=self.id, seq=self.seq, stored_at=self.stored_at,
                                 prev_hash=self.prev_hash, hash=self.hash, record=self.record)


@dataclass(frozen=True)
class WriterStatus:
    """What readiness and the status page show about the store."""

    up: bool  # the database took the last attempt and nothing waits longer than stall_s
    head_seq: int  # the newest result id sealed (journalled)
    committed_seq: int | None  # the newest seq the database is known to hold
    pending: int  # journalled links the database has not committed yet
    oldest_pending_s: float | None  # how long the oldest of them has waited
    last_error: str | None
    last_error_at: datetime | None
    conflict: bool  # the database holds another chain: the writer stopped, an operator must act
    journal: str
    journal_ahead: int = 0  # bytes of zeros written ahead of the journal's appends


class DurableWriter:
    """One station's writer of its audit chain: journal first, database behind it.

    Usage (the station process; one writer per station and data dir)::

        writer = DurableWriter.open(settings.resolved_database_url, station.name,
                                    settings.data_dir, db_wait_s=0.005)
        try:
            sealed = writer.append(record)       # raises StoreFailedError -> Reason.STORE_FAILED
        except StoreFailedError:
            ...
        plc_result_id = sealed.seq               # durable now (journal), whatever the database
        sealed.on_committed(lambda db_id: archive_exec.submit(images.write, db_id, refs, ...))
        writer.status()                          # up/down, pending, last error, head seq
        writer.close()                           # waits a little for pending commits

    ``open`` raises StoreUnavailableError when neither the journal nor the database knows the
    chain's head (a new data dir while the database is down), ChainConflictError when the
    database and the journal disagree, JournalCorruptError when the journal does not verify,
    JournalBusyError when another writer has the journal open.
    """

    def __init__(self, journal: Journal, repo: MeasurementRepository, engine: Engine,
                 db_wait_s: float, retry_max_s: float, stall_s: float,
                 pending: list[Link], committed: tuple[int, str] | None,
                 migrated: bool = False, commit_delay_s: float = 0.0) -> None:
        self.station = repo.station
        self.db_wait_s = db_wait_s
        self.commit_delay_s = commit_delay_s
        self._commit_listeners: list[Callable[[int], object]] = []
        self.retry_max_s = retry_max_s
        self.stall_s = stall_s
        self._journal = journal
        self._repo = repo
        self._engine = engine
        self._append_lock = threading.Lock()  # one append at a time: seq, journal, queue
        self._cond = threading.Condition()  # the queue and the status below
        self._queue: deque[tuple[Link, _Commit, float]] = deque(
            (link, _Commit(), time.monotonic()) for link in pending)
        self._committed = committed
        # migrated at open (a fresh database has no head yet, but its schema is there): the
        # first insert need not migrate again (it cost the first trigger its commit wait)
        self._migrated = migrated or committed is not None
        self._up = self._migrated
        self._last_error: str | None = None
        self._last_error_at: datetime | None = None
        self._conflict = False
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"store-writer-{self.station}",
                                        daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, url: str, station: str, data_dir: Path, *, db_wait_s: float = 0.005,
             sqlite_synchronous: str = "FULL", connect_timeout_s: float = 2.0,
             statement_timeout_s: float = 5.0, sqlite_busy_timeout_s: float = 1.0,
             retry_max_s: float = 2.0, stall_s: float = 2.0,
             segment_entries: int = 1000, journal_ahead: int = PREALLOCATE,
             outbox: OutboxRows | None = None, commit_delay_s: float = 0.0) -> DurableWriter:
        """Open the journal, learn the head (max of journal and database), start the thread.

        With ``outbox`` (server/store/outbox.py), every link the thread inserts (the journal's
        replay too) gets its outbox rows in the insert's transaction. With ``commit_delay_s``,
        the thread inserts a link no sooner than that after its append: the appending thread's
        next steps (a link's answer) do not share the GIL with the insert's ~2 ms of Python."""
        if not 0 <= db_wait_s <= 1:
            raise ValueError(f"db_wait_s must be within 0-1 s, got {db_wait_s}")
        if not 0 <= commit_delay_s <= 1 or (commit_delay_s and db_wait_s):
            raise ValueError(f"commit_delay_s must be within 0-1 s and needs db_wait_s 0, got "
                             f"{commit_delay_s} (db_wait_s {db_wait_s})")
        journal = Journal.open(journal_dir(data_dir, station), station, segment_entries,
                               journal_ahead)
        engine = _writer_engine(url, sqlite_synchronous, connect_timeout_s, statement_timeout_s,
                                sqlite_busy_timeout_s)
        try:
            repo = MeasurementRepository(engine, station, outbox)
            migrated = False  # the schema is there and the database answered
            try:
                migrate(engine)
                db_head: tuple[int, str] | None = repo.head()
                migrated = True
            except Exception as err:  # down, unreachable, frozen past the connect timeout
                db_head, why = None, _one_line(err)
                where = make_url(url).render_as_string(hide_password=True)
                if journal.head is None:
                    raise StoreUnavailableError(
                        f"station {station!r}: the database {where} cannot be reached ({why}) "
                        f"and the journal {journal.directory} is empty, so the chain's head "
                        f"(the next result id) is unknown; start the database and retry"
                    ) from err
                log.warning("station %s: database %s unreachable at start (%s); running on the "
                            "journal, head seq %d", station, where, why, journal.head[0])
            pending = journal.links
            if db_head is not None:
                _check_agreement(repo, journal, db_head)
                if journal.head is None or db_head[0] > journal.head[0]:
                    journal.start(*db_head)
                pending = [link for link in journal.links if link.seq > db_head[0]]
                journal.compact(db_head[0])
            journal.links = []  # read once for the replay; the queue holds what is pending
            writer = cls(journal, repo, engine, db_wait_s, retry_max_s, stall_s, pending,
                         db_head, migrated=migrated, commit_delay_s=commit_delay_s)
        except BaseException:
            journal.close()
            engine.dispose()
            raise
        if pending:
            log.info("station %s: %d journalled records to replay into the database (seq %d-%d)",
                     station, len(pending), pending[0].seq, pending[-1].seq)
        return writer

    # ------------------------------------------------------------------ the trigger path
    def append(self, record: MeasurementRecord) -> Sealed:
        """Seal, journal and queue ``record``; wait for its commit at most ``db_wait_s``.

        Raises StoreFailedError (nothing sealed, the head unchanged) when the journal refuses it.
        """
        if record.station != self.station:
            raise ValueError(
                f"record of station {record.station!r} given to the writer of {self.station!r}"
            )
        record = normalized(record)
        record_json = record.model_dump(mode="json")
        with self._append_lock:
            head = self._journal.head
            assert head is not None
            link = seal_link(self.station, head[0] + 1, head[1], datetime.now(UTC), record,
                             record_json)
            t0 = time.perf_counter()
            try:
                self._journal.append(link)
            except OSError as err:
                raise StoreFailedError(
                    f"station {self.station!r}: the journal {self._journal.directory} could not "
                    f"take seq {link.seq}: {err}"
                ) from err
            journal_ms = (time.perf_counter() - t0) * 1e3
            commit = _Commit()
            with self._cond:
                self._queue.append((link, commit, time.monotonic()))
                self._cond.notify_all()
        if self.db_wait_s > 0:
            commit.wait(self.db_wait_s)
        return Sealed(link, commit, journal_ms)

    def wait_journal_ahead(self, timeout_s: float) -> bool:
        """Wait until the journal's zeros ahead are written (:meth:`Journal.wait_ahead`)."""
        return self._journal.wait_ahead(timeout_s)

    def rehearse(self, record: MeasurementRecord) -> None:
        """The append's own work on ``record`` (normalise, seal, encode the journal line) with
        nothing kept: no seq taken, nothing written. The station runs it before it is ready, so
        that its first real append does not run this code cold."""
        record = normalized(record)
        head = self._journal.head or (0, "0" * 64)
        self._journal.encode(seal_link(self.station, head[0] + 1, head[1], datetime.now(UTC),
                                       record, record.model_dump(mode="json")))

    # ------------------------------------------------------------------ the database thread
    def _run(self) -> None:
        backoff = 0.05
        while not self._closing.is_set():
            with self._cond:
                while not self._closing.is_set():
                    if not self._queue:
                        self._cond.wait()
                        continue
                    hold = self._queue[0][2] + self.commit_delay_s - time.monotonic()
                    if hold <= 0:
                        break
                    self._cond.wait(hold)
                batch = [item for _, item in zip(range(_BATCH), self._queue, strict=False)]
            if not batch:
                continue
            try:
                if not self._migrated:
                    migrate(self._engine)
                    self._migrated = True
                ids = self._repo.insert_links([link for link, _, _ in batch])
            except ChainConflictError as err:
                self._failed(err, conflict=True)
                log.error("station %s: chain conflict, the database writer stops: %s",
                          self.station, err)
                return
            except Exception as err:  # the database is down or refuses: retry, keep order
                self._failed(err, conflict=False)
                log.warning("station %s: database insert of seq %d failed (%s); retry in %.2f s",
                            self.station, batch[0][0].seq, _one_line(err), backoff)
                self._closing.wait(backoff)
                backoff = min(backoff * 2, self.retry_max_s)
                continue
            backoff = 0.05
            with self._cond:
                for _ in batch:
                    self._queue.popleft()
                last = batch[-1][0]
                self._committed = (last.seq, last.hash)
                self._up = True
                self._cond.notify_all()
            for (_, commit, _), db_id in zip(batch, ids, strict=True):
                commit.set(db_id)
            for listen in list(self._commit_listeners):
                try:
                    listen(last.seq)
                except Exception:
                    log.exception("station %s: a commit listener failed", self.station)
            if self._closing.is_set():  # closed while a frozen database held this insert
                return
            try:
                self._journal.compact(last.seq)
            except OSError as err:
                log.warning("journal %s: compaction failed: %s", self._journal.directory, err)

    def _failed(self, err: Exception, conflict: bool) -> None:
        with self._cond:
            self._up = False
            self._conflict = conflict
            self._last_error = _one_line(err)
            self._last_error_at = datetime.now(UTC)
            self._cond.notify_all()

    def add_commit_listener(self, listen: Callable[[int], object]) -> None:
        """Call ``listen(seq)`` on the database thread after each commit, with the newest seq
        the database now holds (an outbox's rows are there from then on)."""
        self._commit_listeners.append(listen)

    # ------------------------------------------------------------------ status and shutdown
    @property
    def head_seq(self) -> int:
        head = self._journal.head
        return head[0] if head else 0

    @property
    def engine(self) -> Engine:
        """The writer's own engine (bounded connect, statement and lock waits)."""
        return self._engine

    @property
    def journal_dir(self) -> Path:
        return self._journal.directory

    def status(self) -> WriterStatus:
        now = time.monotonic()
        with self._cond:
            oldest = now - self._queue[0][2] if self._queue else None
            return WriterStatus(
                up=self._up and not self._conflict and (oldest is None or oldest < self.stall_s),
                head_seq=self.head_seq,
                committed_seq=self._committed[0] if self._committed else None,
                pending=len(self._queue),
                oldest_pending_s=oldest,
                last_error=self._last_error,
                last_error_at=self._last_error_at,
                conflict=self._conflict,
                journal=str(self._journal.directory),
                journal_ahead=self._journal.space_ahead,
            )

    def flush(self, timeout: float) -> bool:
        """Wait until the database holds every journalled link (True) or ``timeout`` s passed
        or the writer stopped on a conflict (False)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._queue and not self._conflict:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return not self._queue

    def close(self, timeout: float = 2.0) -> bool:
        """Stop the thread after waiting up to ``timeout`` s for pending commits; True when
        nothing was left pending (what is left stays in the journal for the next open)."""
        flushed = self.flush(timeout)
        self._closing.set()
        with self._cond:
            self._cond.notify_all()
        # A frozen database holds the thread in a statement; it is a daemon, the journal has
        # every link, and the next open replays what it did not commit.
        self._thread.join(timeout=1.0)
        with self._append_lock:
            self._journal.close()
        if not self._thread.is_alive():
            self._engine.dispose()
        return flushed


def _writer_engine(url: str, sqlite_synchronous: str, connect_timeout_s: float,
                   statement_timeout_s: float, busy_timeout_s: float) -> Engine:
    """The writer's own engine: bounded connects and statements, apart from the REST pool."""
    parsed = make_url(url)
    if parsed.get_backend_name() == "postgresql":
        options = parsed.query.get("options", "")
        options = (f"{options} " if isinstance(options, str) and options else "") + (
            f"-c statement_timeout={int(statement_timeout_s * 1000)} "
            f"-c lock_timeout={int(statement_timeout_s * 1000)}")
        # A partitioned network drops packets without a reset: the kernel's retransmissions
        # would hold an insert for many minutes; tcp_user_timeout and keepalives end it.
        parsed = parsed.update_query_dict({
            "connect_timeout": str(max(1, round(connect_timeout_s))), "options": options,
            "tcp_user_timeout": str(int(2 * statement_timeout_s * 1000)),
            "keepalives": "1", "keepalives_idle": "5", "keepalives_interval": "2",
            "keepalives_count": "3"})
    engine = create_store_engine(parsed.render_as_string(hide_password=False),
                                 sqlite_synchronous)
    if parsed.get_backend_name() == "sqlite":
        @event.listens_for(engine, "connect")
        def _busy(dbapi_conn: Any, _record: Any) -> None:
            cur = dbapi_conn.cursor()
            cur.execute(f"PRAGMA busy_timeout={int(busy_timeout_s * 1000)}")
            cur.close()
    return engine


def _check_agreement(repo: MeasurementRepository, journal: Journal,
                     db_head: tuple[int, str]) -> None:
    """Refuse to start when the database and the journal hold different chains."""
    head = journal.head
    if head is None:
        return
    if head[0] <= db_head[0]:
        stored = repo.hash_at(head[0]) if head[0] else head[1]
        if stored != head[1]:
            raise ChainConflictError(
                f"station {repo.station!r}: the journal {journal.directory} sealed seq {head[0]} "
                f"as {head[1][:12]}…, the database holds {str(stored)[:12]}… there"
            )
        return
    known = {link.seq: link.hash for link in journal.links}
    if db_head[0] in known and known[db_head[0]] != db_head[1]:
        raise ChainConflictError(
            f"station {repo.station!r}: the database's head seq {db_head[0]} has hash "
            f"{db_head[1][:12]}…, the journal {journal.directory} sealed it as "
            f"{known[db_head[0]][:12]}…"
        )
    first = journal.links[0].seq if journal.links else head[0] + 1
    if db_head[0] + 1 < first:
        raise ChainConflictError(
            f"station {repo.station!r}: the database ends at seq {db_head[0]} but the journal "
            f"{journal.directory} only holds seq {first}-{head[0]}: seq {db_head[0] + 1}-"
            f"{first - 1} are in neither (a database restored from an older backup?)"
        )


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}"[:300]


__all__ = ["DurableWriter", "Sealed", "StoreFailedError", "WriterStatus", "GENESIS"]
