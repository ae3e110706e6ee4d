"""The S7 poll cycle as data, knowing nothing of sockets or clocks: what to read and write, when a
block does not fit, and how long to wait before connecting again.

mvpose is the S7 client (PUT/GET). Every poll it reads the whole trigger block (the layout's
output block, written by the PLC program) in one read request and hands it to the handshake; it
writes the result block (the layout's input block) only when a byte other than the device
heartbeat changed since the PLC acknowledged the last write, and otherwise just the heartbeat
word when it moved. A write is one request: an S7 CPU applies the data of one Write Var job
between two cycles of the PLC program, so the PLC never sees half a result block, as long as the
block fits the negotiated PDU (:func:`check_pdu`). After a (re)connection the first write is the
whole block, whatever the PLC holds: it then holds exactly the handshake's image again.

Sizes from the S7 protocol (S7comm job and ack-data PDUs, header 10 bytes for a job and 12 for an
ack-data; "Read Var" / "Write Var" function 0x04 / 0x05 with one 12-byte any-pointer item):

- a Write Var job of n bytes is 10 + 14 + 4 + n bytes; python-snap7 splits a write longer than
  PDU - 35 bytes into several jobs, so the result block needs a PDU of n + 35 bytes to go as one;
- a Read Var ack-data of n bytes is 12 + 2 + 4 + n bytes (python-snap7 reads up to PDU - 18).
"""

from __future__ import annotations

from dataclasses import dataclass

WRITE_OVERHEAD = 35  # python-snap7's bound per Write Var job (the protocol's own is 28)
READ_OVERHEAD = 18  # header 12, parameter 2, data item header 4


@dataclass(frozen=True)
class Block:
    """One data block range: ``size`` bytes from byte ``start`` of DB ``db``."""

    role: str  # "trigger" or "result", as the messages name it
    db: int
    start: int
    size: int

    @property
    def end(self) -> int:
        return self.start + self.size

    def __str__(self) -> str:
        return f"DB{self.db}.DBB{self.start}..{self.end - 1}"


@dataclass(frozen=True)
class DbWrite:
    """One Write Var job: ``data`` at byte ``start`` of DB ``db``."""

    db: int
    start: int
    data: bytes


class BlockError(ValueError):
    """The PLC's data blocks or its PDU do not fit the layout: the link cannot run until someone
    changes the PLC project (or the station file). The message names the DB, its size and the
    size needed."""


def check_pdu(pdu: int, trigger: Block, result: Block, plc: str) -> None:
    """BlockError unless the trigger block reads and the result block writes in one request each
    with a negotiated PDU of ``pdu`` bytes."""
    need = max(result.size + WRITE_OVERHEAD, trigger.size + READ_OVERHEAD)
    if pdu < need:
        raise BlockError(
            f"PLC {plc}: the negotiated PDU of {pdu} bytes is too small: the result block "
            f"({result}, {result.size} bytes) must be written in one request, which needs a PDU "
            f"of at least {need} bytes (every S7-300/400/1200/1500 CPU offers 240 or more)")


def missing(block: Block, plc: str) -> BlockError:
    """The PLC refused every byte of the block's DB: it has no such DB (or no access to it)."""
    return BlockError(
        f"PLC {plc}: DB{block.db} (the {block.role} block) cannot be read: the PLC has no "
        f"DB{block.db}, or the DB has 'Optimized block access' on; the {block.role} block needs "
        f"bytes {block.start}..{block.end - 1} of it ({block.end} bytes)")


def too_short(block: Block, length: int, plc: str) -> BlockError:
    """The block's DB ends before the block does."""
    return BlockError(
        f"PLC {plc}: DB{block.db} (the {block.role} block) is {length} bytes long; the "
        f"{block.role} block needs bytes {block.start}..{block.end - 1} ({block.end} bytes)")


class ProbeLength:
    """Find how long a DB is with 1-byte reads (bisection): PUT/GET gives no DB length, but a read
    past a DB's end is refused. ``next_offset`` is the byte to try, ``answer(ok)`` says whether
    that read succeeded; ``length`` is the DB's length once ``done`` (0: not even byte 0)."""

    def __init__(self, below: int) -> None:
        """The DB is known to be shorter than ``below`` bytes."""
        self._lo, self._hi = 0, below  # bytes [0, lo) readable; byte hi-1 .. not yet known

    @property
    def done(self) -> bool:
        return self._lo >= self._hi

    @property
    def next_offset(self) -> int:
        return (self._lo + self._hi - 1) // 2

    def answer(self, ok: bool) -> None:
        k = self.next_offset
        if ok:
            self._lo = k + 1
        else:
            self._hi = k

    @property
    def length(self) -> int:
        return self._lo


class ResultWriter:
    """Which write the result block needs now: the whole block once after every (re)connection
    and whenever a byte other than the heartbeat word changed, else the heartbeat word alone
    when it changed, else nothing. ``written`` tells it the PLC acknowledged a write; a write
    that failed leaves the last acknowledged image, so it is written again."""

    def __init__(self, block: Block, heartbeat: slice) -> None:
        """``heartbeat``: the device heartbeat word's bytes in the block."""
        self.block = block
        self.heartbeat = heartbeat
        self._plc: bytes | None = None  # what the PLC holds (as far as we know)

    def reset(self) -> None:
        """A new connection: the PLC's copy is unknown, the next write is the whole block."""
        self._plc = None

    def next_write(self, image: bytes) -> DbWrite | None:
        if len(image) != self.block.size:
            raise ValueError(f"result image of {len(image)} bytes, the block has "
                             f"{self.block.size}")
        held = self._plc
        if held is None or _without(held, self.heartbeat) != _without(image, self.heartbeat):
            return DbWrite(self.block.db, self.block.start, bytes(image))
        if held[self.heartbeat] != image[self.heartbeat]:
            return DbWrite(self.block.db, self.block.start + (self.heartbeat.start or 0),
                           bytes(image[self.heartbeat]))
        return None

    def written(self, write: DbWrite) -> None:
        offset = write.start - self.block.start
        if offset == 0 and len(write.data) == self.block.size:
            self._plc = write.data
        elif self._plc is not None:
            held = bytearray(self._plc)
            held[offset: offset + len(write.data)] = write.data
            self._plc = bytes(held)


def _without(image: bytes, cut: slice) -> bytes:
    return image[: cut.start] + image[cut.stop:]


class Backoff:
    """Waits before connecting again: ``first`` seconds, doubling up to ``limit``; ``reset``
    after a connection that worked."""

    def __init__(self, first: float, limit: float) -> None:
        self.first, self.limit = first, limit
        self._next = first

    def next(self) -> float:
        wait = self._next
        self._next = min(self._next * 2, self.limit)
        return wait

    def reset(self) -> None:
        self._next = self.first


class Outage:
    """Whether the PLC is reachable, and whether a problem is news: one log line per outage, not
    one per attempt, and one more only when its kind changes (a PLC that was unreachable
    answers now, but its DB does not fit: the operator needs that message)."""

    def __init__(self) -> None:
        self.up = False
        self.reason = ""
        self.outages = 0
        self._told: str | None = None  # the kind of problem the log has told of in this outage

    def connected(self) -> bool:
        """The link works again; True when that ends an outage that was reported."""
        was_down = self._told is not None
        self.up, self.reason, self._told = True, "", None
        return was_down

    def lost(self, reason: str, kind: str = "lost") -> bool:
        """A connection attempt or a working connection failed (``kind``: "lost" for the
        connection, "block" for a DB or PDU that does not fit); True when this is news."""
        if self.up or self._told is None:
            self.outages += 1
        self.up = False
        self.reason = reason
        news = kind != self._told
        self._told = kind
        return news
