"""Where the station's records go: the durable writer (journal first, database behind it).

:class:`RecordSink` is what the station needs of it; :class:`WriterSink` is the production one
(server.store.writer), and the MQTT publisher's sink (server.station.mqtt) is one with an outbox.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from server.state import Services
from server.store.outbox import OutboxRows
from server.store.schemas import MeasurementRecord


@dataclass(frozen=True)
class Appended:
    """A record made durable: its result id (the chain's seq) and its database id, if known."""

    result_id: int
    db_id: int | None
    # calls back with the database id once the record is in the database (at once if it is)
    on_committed: Callable[[Callable[[int], object]], None] | None = None


class RecordSink(Protocol):
    def append(self, record: MeasurementRecord) -> Appended: ...

    def rehearse(self, record: MeasurementRecord) -> None: ...

    def settle(self, timeout_s: float) -> bool: ...

    def status(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


class WriterSink:
    """The station's durable writer (server.store.writer): the journal first, the database
    behind it. An append never waits for the database; the database thread inserts a record
    ``commit_delay_s`` after its append, once the link has answered (its ~2 ms of Python would
    otherwise hold the GIL while the answer goes out). With ``outbox`` (the MQTT publisher's),
    each record's messages are inserted in its transaction."""

    def __init__(self, services: Services, commit_delay_s: float = 0.005,
                 outbox: OutboxRows | None = None) -> None:
        from server.store.writer import DurableWriter

        self.services = services
        self.outbox = outbox
        s = services.settings
        self.writer = DurableWriter.open(s.resolved_database_url, services.station_name,
                                         s.data_dir, db_wait_s=0.0,
                                         commit_delay_s=commit_delay_s,
                                         sqlite_synchronous=s.sqlite_synchronous, outbox=outbox)

    def append(self, record: MeasurementRecord) -> Appended:
        sealed = self.writer.append(record)  # StoreFailedError: the station answers STORE_FAILED
        self.services.metrics.observe(record, sealed.seq)
        return Appended(result_id=sealed.seq, db_id=sealed.id, on_committed=sealed.on_committed)

    def rehearse(self, record: MeasurementRecord) -> None:
        self.writer.rehearse(record)

    def settle(self, timeout_s: float) -> bool:
        """Wait for the journal's zeros ahead: the first appends then share the disk with no
        zero piece being written."""
        return self.writer.wait_journal_ahead(timeout_s)

    def status(self) -> dict[str, Any]:
        st = self.writer.status()
        return {"up": st.up, "head_seq": st.head_seq, "committed_seq": st.committed_seq,
                "pending": st.pending, "oldest_pending_s": st.oldest_pending_s,
                "last_error": st.last_error, "conflict": st.conflict, "journal": st.journal}

    def flush(self, timeout_s: float) -> bool:
        return self.writer.flush(timeout_s)

    def close(self) -> None:
        self.writer.close()
