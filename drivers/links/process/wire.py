"""The socket between the station and a link's child process: its descriptors, its timing rules,
the handler calls a child may make, and the frames (length, pickle) both sides write on it."""

from __future__ import annotations

import asyncio
import pickle
import struct
from typing import Any

CHILD_FD = 3  # the socket's descriptor in the child
ANSWER_FD = 4  # the answers' socket's descriptor in the child (see TriggerPost)
STATUS_EVERY_S = 0.2  # the child sends its status when it changed, at most this often
RESTART_S = (1.0, 30.0)  # first and longest wait before a dead child is started again
START_S = 25.0  # a child whose link has not started this long after its spawn is killed
STOP_S = 3.0  # a child that has not read "stop" and ended this long after it is killed
BACKLOG_BYTES = 4 << 20  # a child that leaves this much unread (frozen, stopped) is killed
HEADER = struct.Struct("!I")
MAX_FRAME = 64 << 20
# the StationHandler calls a child may make (its answers go back as replies)
CALLS = frozenset({"measure", "record_failure", "select_recipe", "teach_reference", "reset",
                   "verify", "handeye_begin", "handeye_add_pose", "handeye_calculate",
                   "unselect_recipe", "recipes", "get_result", "find_results", "calibrations",
                   "activate_calibration"})


class Wire:
    """Pickled frames over one stream; writes go out in order on the owning loop."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.closed = False

    def send(self, *message: Any) -> None:
        if self.closed or self.writer.is_closing():
            return
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self.writer.write(HEADER.pack(len(data)) + data)

    def backlog(self) -> int:
        """Bytes written that the other side has not read yet (beyond the socket's buffer)."""
        return self.writer.transport.get_write_buffer_size()

    async def read(self) -> tuple[Any, ...] | None:
        """The next message; None when the other side has gone."""
        try:
            (size,) = HEADER.unpack(await self.reader.readexactly(HEADER.size))
            if size > MAX_FRAME:
                raise ValueError(f"a frame of {size} bytes (at most {MAX_FRAME})")
            message: tuple[Any, ...] = pickle.loads(await self.reader.readexactly(size))
        except (asyncio.IncompleteReadError, ConnectionError):
            return None
        return message

    def close(self) -> None:
        self.closed = True
        self.writer.close()


def portable(err: BaseException) -> BaseException:
    """``err`` if it survives pickling, else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(err))
    except Exception:  # noqa: BLE001 - any exception a handler raised
        return RuntimeError(f"{type(err).__name__}: {err}")
    return err
