"""A link backend in a process of its own, with the station's :class:`StationHandler` reached
over a socket: the station keeps one GIL for its trigger path.

A backend whose protocol work is pure Python and heavy per result (OPC UA: each result event is
built, deep-copied and encoded by asyncua) or frequent (Modbus/TCP: a PLC polls its status every
few milliseconds) would take the station process's GIL while the trigger thread waits for it.
Listed in ``drivers.links.OWN_PROCESS``, it runs in a child process instead:

- :class:`ProcessLink` stands for it in the station (on the station's loop): it starts the child,
  serves the child's handler calls with the station's handler (also while the child's link
  starts), forwards each result to it, and shows the child's status, readiness and line state.
  A child that dies is started again (backoff 1 s to 30 s); the station and its other links go
  on meanwhile. A child that does not answer its start within ``START_S``, or leaves
  ``BACKLOG_BYTES`` unread (frozen), is killed.
- In the child, ``python -m drivers.links.process <backend>``, the backend runs unchanged against
  :class:`RemoteHandler`, a StationHandler whose calls cross the socket. What the handler answers
  without a call (the selected recipe, its robot convention) comes with every reply and with each
  recipe change.
- A trigger takes a second socket (SOCK_SEQPACKET; :class:`~.post.TriggerPost`) both ways: the
  child posts the request there (when none of its calls waits for an answer, so it never overtakes
  one); a thread of the station's side reads it and, from a handler that is
  :class:`~drivers.links.base.AnswersEarly` (the station), starts it at once
  (``measure_posted``); the outcome is posted back by the thread that recorded it, right after
  the append. Neither way waits for the station loop.

The child is started with ``posix_spawn`` under the normal scheduling policy: a station whose
threads run under SCHED_FIFO does not pass its real-time priority on, unless the backend is in
``drivers.links.REALTIME`` (the Modbus link: the PLC's handshake is the trigger path, and its
polls must not wait for the station PC's other work); that child runs at the station loop's
priority. It ends when its socket closes, so a station killed with SIGKILL leaves no child
behind. The socket is a private socketpair between the station and its own child; messages are
pickled frames (length, pickle) of this package's tuples and the seam's dataclasses; a result
event crosses as its own JSON (``ResultEvent.to_json``). This package is the only one that knows
them: :mod:`.wire` (the socket and its frames), :mod:`.station` (the station's side),
:mod:`.child` (the child's), :mod:`.post` (the triggers' socket, the station's side).
"""

from .station import ProcessLink, hosted
from .wire import START_S, STOP_S

__all__ = ["START_S", "STOP_S", "ProcessLink", "hosted"]
