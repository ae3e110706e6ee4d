"""The station's write-ahead journal: every sealed link, fsynced, before the database sees it.

A journal is a folder of segments, ``<data_dir>/journal/<station>/<after_seq>.jsonl``, one JSON
object a line. A segment's first line is its header: the link the segment continues from,
``{"journal": 1, "station": S, "after_seq": n, "after_hash": h}``; every further line is one link,
``{"seq": n + 1, "prev_hash": …, "hash": …, "body": …}`` with ``body`` the exact text the hash
seals (server/store/chain.py). A new segment starts when the current one holds
``segment_entries`` links; a segment is deleted once the database holds each of its links and a
newer segment exists, so the newest link (the chain's head) always stays on disk.

A segment file is longer than its lines: NUL bytes follow the last line, written (and synced)
ahead of the appends by a thread of the journal's own, so that an append overwrites blocks the
file already has and its ``fdatasync`` flushes the data alone. Growing the file instead changes
its size, which waits for the file system's own journal commit (ext4's jbd2, a normal-priority
kernel thread): on a busy two-core PC that made an append take 3-12 ms instead of 0.3-1 ms. The
thread keeps up to :data:`PREALLOCATE` bytes ahead, in synced pieces of :data:`CHUNK` (an
append's ``fdatasync`` flushes whatever of the file is dirty, so the zeros must never be much of
it). The first NUL byte of a segment ends its lines (JSON text never holds one).

Only the last line of the last segment can be torn (the process died in the append, which had
therefore not returned its seq): it is cut off at open with a warning. Anything else that does
not verify (a line that is not JSON, a seq out of order, a hash that the body does not give)
is :class:`JournalCorruptError`, naming the file, the line and what is wrong.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server.store.chain import canonical_json
from server.store.measurements import Link, link_from_body

log = logging.getLogger(__name__)

FORMAT = 1
#: zeros the journal's thread keeps written ahead of the appends (it tops up when less than
#: half is left)
PREALLOCATE = 1024 * 1024
#: the thread writes and syncs this much at a time
CHUNK = 64 * 1024
#: where the lines have caught up with the zeros (a new segment), the first piece is this small,
#: so that an append meanwhile waits for it briefly
FIRST_PIECE = 8 * 1024
_STATION = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
_SEGMENT = re.compile(r"^(\d{20})\.jsonl$")


class JournalCorruptError(Exception):
    """The journal on disk does not verify; the message names the file, line and problem."""


class JournalBusyError(Exception):
    """Another writer (process or object) has this journal open."""


@dataclass
class _Segment:
    path: Path
    after_seq: int
    last_seq: int  # after_seq when it holds no link yet
    entries: int
    end: int = 0  # bytes of lines when read at open (the NULs after them: space written ahead)


def journal_dir(data_dir: Path, station: str) -> Path:
    """Where the journal of ``station`` lives under the data dir."""
    if not _STATION.match(station) or station in (".", ".."):
        raise ValueError(f"station name {station!r} cannot name a journal folder")
    return Path(data_dir) / "journal" / station


class Journal:
    """Append-only, fsynced segments of one station's chain. Not thread-safe for appends (the
    writer serialises them); :meth:`compact` may run on another thread."""

    def __init__(self, directory: Path, station: str, segment_entries: int,
                 ahead: int = PREALLOCATE) -> None:
        if segment_entries < 1:
            raise ValueError(f"segment_entries must be >= 1, got {segment_entries}")
        self.directory = directory
        self.station = station
        self.segment_entries = segment_entries
        self.ahead = ahead  # PREALLOCATE; 0: no zeros ahead, every append grows the file
        self._segments: list[_Segment] = []
        self._fd: int | None = None  # the last segment, open for writing
        self._size = 0  # where its lines end (the next append's offset)
        # [_zero_from, _zero_to): synced zeros an append may overwrite (from <= _size: it may)
        self._zero_from = 0
        self._zero_to = 0
        # the zeroing thread's work, between it, appends outside the zeros and a new segment
        self._alloc = threading.Condition()
        self._zeroing: tuple[int, int, int] | None = None  # (fd, lo, hi) being written now
        self._retired: int | None = None  # a finished segment's fd, closed when its zeroing ends
        self._wake = threading.Event()
        self._idle = False  # the thread has written all it was woken for (until the next wake)
        self._stopping = False
        self._ahead: threading.Thread | None = None
        self._head: tuple[int, str] | None = None
        self._broken: OSError | None = None
        self._lock = threading.Lock()  # the segment list, between append and compact
        self._lock_fd: int | None = None  # holds the folder's flock while open
        self.links: list[Link] = []  # what open() read back, oldest first

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, directory: Path, station: str, segment_entries: int = 1000,
             ahead: int = PREALLOCATE) -> Journal:
        """Read and verify every segment (cutting a torn last line); create the folder if new."""
        journal = cls(Path(directory), station, segment_entries, ahead)
        _make_dirs(journal.directory)
        journal._lock_folder()
        try:
            names = sorted(p.name for p in journal.directory.iterdir() if _SEGMENT.match(p.name))
            for k, name in enumerate(names):
                journal._read_segment(journal.directory / name, last=k == len(names) - 1)
            if journal._segments:
                journal._open_last()
        except BaseException:
            journal.close()
            raise
        return journal

    def _lock_folder(self) -> None:
        """One writer per journal: a second one (a station started twice) would fork the chain.
        The lock is the kernel's (flock), so it ends with the process however that ends."""
        path = self.directory / "lock"
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise JournalBusyError(
                f"journal {self.directory} is in use by another writer (pid {holder}); "
                f"one station runs one writer"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._lock_fd = fd

    def _read_segment(self, path: Path, last: bool) -> None:
        raw_file = path.read_bytes()
        nul = raw_file.find(b"\0")
        data = raw_file if nul < 0 else raw_file[:nul]
        lines = data.split(b"\n")
        good_end = 0  # byte offset after the last line that verified
        header: dict[str, Any] | None = None
        links: list[Link] = []
        prev: tuple[int, str] | None = None
        offset = 0
        for number, raw in enumerate(lines, start=1):
            end = offset + len(raw) + 1
            complete = end <= len(data)  # the last chunk has no newline after it
            if not raw and not complete:
                break
            try:
                if not complete:
                    raise ValueError("line has no end (torn write)")
                obj = json.loads(raw)
                if header is None:
                    header = self._check_header(obj)
                    prev = (header["after_seq"], header["after_hash"])
                else:
                    assert prev is not None
                    links.append(self._check_link(obj, prev))
                    prev = (links[-1].seq, links[-1].hash)
            except (ValueError, KeyError, TypeError) as err:
                rest = lines[number:]
                if last and not any(_parses(r) for r in rest):
                    log.warning(
                        "journal %s: line %d does not verify (%s); cutting %d torn bytes at "
                        "offset %d (an append that never returned)",
                        path, number, err, len(data) - offset, offset,
                    )
                    break
                raise JournalCorruptError(f"journal {path}: line {number}: {err}") from None
            good_end = end
            offset = end
        if header is None:
            if last:  # the segment's creation was torn: its first link never returned
                log.warning("journal %s: no complete header; removing the torn segment", path)
                path.unlink()
                _fsync_dir(path.parent)
                return
            raise JournalCorruptError(f"journal {path}: no header line")
        if raw_file[good_end:].strip(b"\0"):  # a torn line (or its pieces): zeros instead
            with open(path, "r+b") as f:
                f.seek(good_end)
                f.write(bytes(len(raw_file) - good_end))
                f.flush()
                os.fsync(f.fileno())
        after = int(header["after_seq"])
        if self._segments and after < self._segments[-1].last_seq:
            raise JournalCorruptError(
                f"journal {path}: continues from seq {after} but the segment before it reaches "
                f"seq {self._segments[-1].last_seq}"
            )
        if self._head is not None and after == self._head[0] and header["after_hash"] != (
            self._head[1]
        ):
            raise JournalCorruptError(
                f"journal {path}: continues from seq {after} with hash "
                f"{header['after_hash'][:12]}…, the segment before sealed it as "
                f"{self._head[1][:12]}…"
            )
        assert prev is not None
        self._segments.append(_Segment(path, after, prev[0], len(links), good_end))
        self.links += links
        self._head = prev

    def _check_header(self, obj: Any) -> dict[str, Any]:
        if not isinstance(obj, dict) or obj.get("journal") != FORMAT:
            raise ValueError(f"not a journal header of format {FORMAT}: {str(obj)[:80]}")
        if obj.get("station") != self.station:
            raise ValueError(f"header names station {obj.get('station')!r}, not {self.station!r}")
        if not isinstance(obj.get("after_seq"), int) or obj["after_seq"] < 0:
            raise ValueError(f"header after_seq {obj.get('after_seq')!r} is not a seq")
        if not isinstance(obj.get("after_hash"), str) or len(obj["after_hash"]) != 64:
            raise ValueError(f"header after_hash {obj.get('after_hash')!r} is not a hash")
        return obj

    def _check_link(self, obj: Any, prev: tuple[int, str]) -> Link:
        if not isinstance(obj, dict):
            raise ValueError(f"not a link: {str(obj)[:80]}")
        if obj["seq"] != prev[0] + 1:
            raise ValueError(f"seq {obj['seq']} follows seq {prev[0]}")
        if obj["prev_hash"] != prev[1]:
            raise ValueError(f"seq {obj['seq']}: prev_hash is not the hash of seq {prev[0]}")
        link = link_from_body(obj["prev_hash"], obj["hash"], obj["body"])
        if link.seq != obj["seq"] or link.station != self.station:
            raise ValueError(
                f"seq {obj['seq']}: body names station {link.station!r} seq {link.seq}"
            )
        return link

    def _open_last(self) -> None:
        seg = self._segments[-1]
        self._fd = os.open(seg.path, os.O_WRONLY)
        self._size = seg.end
        # every byte after the lines is zero (a torn line was zeroed at open)
        self._zero_from, self._zero_to = seg.end, max(seg.end, os.fstat(self._fd).st_size)
        self._wake.set()
        self._start_ahead()

    # ------------------------------------------------------------------ state
    @property
    def head(self) -> tuple[int, str] | None:
        """(seq, hash) of the newest link (or segment header) on disk; None for a new journal."""
        return self._head

    @property
    def space_ahead(self) -> int:
        """Bytes of synced zeros the next appends overwrite (0 while a new segment has none)."""
        with self._alloc:
            return self._zero_to - self._size if self._zero_from <= self._size else 0

    def wait_ahead(self, timeout_s: float) -> bool:
        """Wait until the journal's thread has written the zeros it was last woken for (at open:
        up to ``ahead`` of them), so that the next appends overwrite zeros and share the disk with
        no zero piece being written; False if not within ``timeout_s`` or none could be written."""
        if self.ahead <= 0:
            return True
        with self._alloc:
            settled = self._alloc.wait_for(
                lambda: self._stopping or (self._idle and not self._wake.is_set()), timeout_s)
            zeros = self._zero_from <= self._size < self._zero_to
            return settled and self._fd is not None and zeros

    @property
    def segments(self) -> list[Path]:
        with self._lock:
            return [s.path for s in self._segments]

    # ------------------------------------------------------------------ writing
    def start(self, after_seq: int, after_hash: str) -> None:
        """Begin a segment continuing from (after_seq, after_hash): the head the database knows,
        when it is ahead of this journal (or the journal is new)."""
        if self._head is not None and after_seq <= self._head[0]:
            raise ValueError(f"journal head is seq {self._head[0]}; cannot restart at {after_seq}")
        self._new_segment(after_seq, after_hash, b"")

    def append(self, link: Link) -> None:
        """Write the link and fsync it; on any failure nothing of it stays and OSError is raised."""
        if self._broken is not None:
            raise OSError(f"journal {self.directory} takes no more links: {self._broken}")
        head = self._head
        if head is None:
            raise ValueError(f"journal {self.directory} has no head; start() it first")
        if (link.seq, link.prev_hash) != (head[0] + 1, head[1]):
            raise ValueError(
                f"link seq {link.seq} does not follow the journal head seq {head[0]}"
            )
        line = _line(link)
        seg = self._segments[-1]
        if seg.entries >= self.segment_entries:
            self._new_segment(head[0], head[1], line)
        else:
            end = self._size + len(line)
            if self._zero_from <= self._size and end <= self._zero_to:
                self._put(line)  # over synced zeros: the thread only ever writes past them
            else:
                # Not over zeros (the file grows): never into the piece the thread is writing,
                # and it may not start one (at the lines' end) until this line is down.
                with self._alloc:
                    self._alloc.wait_for(lambda: not self._overlaps(self._size, end))
                    self._put(line)
            self._size += len(line)
            seg.entries += 1
        self._segments[-1].last_seq = link.seq
        self._head = (link.seq, link.hash)
        if self.ahead and self._zero_to - self._size < self.ahead // 2:
            self._wake.set()

    def _put(self, line: bytes) -> None:
        """Write ``line`` at the lines' end and fdatasync it; on failure nothing of it stays."""
        assert self._fd is not None
        try:
            _write_at(self._fd, line, self._size)
            os.fdatasync(self._fd)
        except OSError as err:
            self._undo(err, len(line))
            raise

    def _overlaps(self, lo: int, hi: int) -> bool:
        z = self._zeroing
        return z is not None and z[0] == self._fd and z[1] < hi and lo < z[2]

    @staticmethod
    def encode(link: Link) -> bytes:
        """The line an append writes for ``link``."""
        return _line(link)

    def _undo(self, err: OSError, length: int) -> None:
        """Overwrite with zeros whatever part of the failed line reached the file."""
        assert self._fd is not None
        try:
            reached = min(os.fstat(self._fd).st_size, self._size + length) - self._size
            if reached > 0:  # zeros over exactly what reached the file (it must not grow)
                _write_at(self._fd, bytes(reached), self._size)
                os.fdatasync(self._fd)
        except OSError as again:
            self._broken = OSError(f"a failed append could not be cut off ({again})")
            log.error("journal %s: cannot cut a failed append (%s) after %s",
                      self.directory, again, err)

    def _new_segment(self, after_seq: int, after_hash: str, first: bytes) -> None:
        header = canonical_json({"journal": FORMAT, "station": self.station,
                                 "after_seq": after_seq, "after_hash": after_hash})
        path = self.directory / f"{after_seq:020d}.jsonl"
        data = header.encode() + b"\n" + first
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            _write_at(fd, data, 0)
            os.fsync(fd)
            _fsync_dir(self.directory)
        except OSError:
            os.close(fd)
            path.unlink(missing_ok=True)
            raise
        with self._alloc:
            old = self._fd
            with self._lock:
                self._segments.append(_Segment(path, after_seq, after_seq, 1 if first else 0,
                                               len(data)))
            self._fd, self._size = fd, len(data)
            self._zero_from = self._zero_to = len(data)  # the thread starts the zeros
            if old is not None and self._zeroing is not None and self._zeroing[0] == old:
                self._retired, old = old, None  # the thread closes it when done
        if old is not None:
            os.close(old)
        if not first:
            self._head = (after_seq, after_hash)
        self._wake.set()
        self._start_ahead()

    def _start_ahead(self) -> None:
        if self._ahead is None and self.ahead > 0:
            self._ahead = threading.Thread(target=self._write_ahead, daemon=True,
                                           name=f"journal-ahead-{self.station}")
            self._ahead.start()

    def _write_ahead(self) -> None:
        """The journal's thread: keep up to ``ahead`` bytes of synced zeros after the lines,
        written a CHUNK at a time outside the lock, always past the lines."""
        while True:
            self._wake.wait()
            with self._alloc:  # not idle before the wake is cleared: wait_ahead sees one or both
                self._idle = False
                self._wake.clear()
            while True:
                with self._alloc:
                    if self._stopping or self._fd is None:
                        return
                    if self._zero_to - self._size >= self.ahead:
                        self._idle = not self._wake.is_set()
                        self._alloc.notify_all()
                        break
                    fd = self._fd
                    piece = CHUNK
                    if self._zero_to <= self._size:  # the lines reached the zeros' end
                        # a small first piece: an append meanwhile waits for it, not for a CHUNK
                        self._zero_from = self._zero_to = self._size
                        piece = FIRST_PIECE
                    lo = self._zero_to
                    self._zeroing = (fd, lo, lo + piece)
                done = False
                try:
                    _write_at(fd, bytes(piece), lo)
                    os.fdatasync(fd)
                    done = True
                except OSError as err:  # appends go on growing the file: slower, not wrong
                    log.warning("journal %s: cannot write space ahead (%s)", self.directory, err)
                with self._alloc:
                    self._zeroing = None
                    if done and self._fd == fd and self._zero_to == lo:
                        self._zero_to = lo + piece
                    if self._retired is not None:
                        os.close(self._retired)
                        self._retired = None
                    if not done:
                        self._idle = not self._wake.is_set()
                    self._alloc.notify_all()
                if not done:
                    break

    def compact(self, committed_seq: int) -> int:
        """Delete the segments the database holds entirely (never the newest); how many."""
        with self._lock:
            done = [s for s in self._segments[:-1] if s.last_seq <= committed_seq]
            self._segments = [s for s in self._segments if s not in done]
        for s in done:
            s.path.unlink(missing_ok=True)
        if done:
            _fsync_dir(self.directory)
        return len(done)

    def close(self) -> None:
        with self._alloc:
            self._stopping = True
            self._alloc.notify_all()
        self._wake.set()
        if self._ahead is not None and self._ahead is not threading.current_thread():
            self._ahead.join(timeout=5)
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None
        self._broken = self._broken or OSError("it was closed")


def _line(link: Link) -> bytes:
    return (canonical_json({"seq": link.seq, "prev_hash": link.prev_hash, "hash": link.hash,
                            "body": link.body}) + "\n").encode()


def _parses(raw: bytes) -> bool:
    try:
        return isinstance(json.loads(raw), dict)
    except ValueError:
        return False


def _write_at(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        n = os.pwrite(fd, view, offset)
        view = view[n:]
        offset += n


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _make_dirs(path: Path) -> None:
    missing = []
    p = path
    while not p.exists():
        missing.append(p)
        p = p.parent
    path.mkdir(parents=True, exist_ok=True)
    for p in reversed(missing):  # each new folder's name is durable in its parent
        _fsync_dir(p.parent)
