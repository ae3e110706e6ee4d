"""The triggers' socket between the station and a link's child process, the station's side:
requests read on a thread of its own, outcomes posted from the thread that recorded them."""

from __future__ import annotations

import contextlib
import logging
import pickle
import socket
import threading
from collections.abc import Callable
from typing import Any

from .wire import STOP_S

log = logging.getLogger(__name__)


class TriggerPost:
    """The station's side of the triggers' socket (SOCK_SEQPACKET: each message whole or not
    at all). The child posts its trigger requests on it; a thread of the station's own reads
    them and starts each at once (``on_request``), without the station loop. A trigger's
    outcome goes back on it from the thread that recorded it (the trigger thread), without
    waiting for the station loop to hear of it first; a send never blocks, and one that fails
    (the child is not reading: frozen, or gone) leaves the reply to the wire, whose backlog
    rule then deals with the child."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._reader: threading.Thread | None = None

    def open(self, sock: socket.socket,
             on_request: Callable[[tuple[Any, ...]], None]) -> None:
        sock.setblocking(True)  # the reader waits in recv; sends say MSG_DONTWAIT
        reader = threading.Thread(target=self._read, args=(sock.dup(), on_request),
                                  name="link-triggers", daemon=True)
        with self._lock:
            self._sock, self._reader = sock, reader
        reader.start()  # at the priority of the thread that starts it: the station loop's

    def send(self, message: tuple[Any, ...]) -> bool:
        try:
            data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:  # noqa: BLE001 - the wire's path reports what cannot cross
            return False
        with self._lock:
            if self._sock is None:
                return False
            try:
                self._sock.send(data, socket.MSG_DONTWAIT)
            except OSError:
                return False
        return True

    @staticmethod
    def _read(sock: socket.socket, on_request: Callable[[tuple[Any, ...]], None]) -> None:
        with sock:
            while True:
                try:
                    data = sock.recv(1 << 16)
                except OSError:
                    return
                if not data:  # the child has gone, or close() shut the socket
                    return
                try:
                    message = pickle.loads(data)
                    if message[0] != "measure":
                        raise ValueError(f"unknown message {message[0]!r}")
                    on_request(message)
                except Exception:
                    log.exception("a trigger request from the link's process failed")

    def close(self) -> None:
        with self._lock:
            sock, self._sock = self._sock, None
            reader, self._reader = self._reader, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)  # wakes the reader: its recv ends
            sock.close()
        if reader is not None and reader is not threading.current_thread():
            reader.join(timeout=STOP_S)
