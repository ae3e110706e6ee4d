"""A PROFINET process of its own (the device's, our IO-controller's) and the SEQPACKET
socketpair it talks over: one message a packet, a kind byte and its body, never a round trip.
The process is ``python -m <module> <config JSON> <descriptor of its end of the pair>``."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

#: the folder the ``drivers`` package is in: the child's working directory
ROOT = str(Path(__file__).resolve().parents[3])


def spawn(module: str, cfg: dict[str, Any],
          prefix: Sequence[str] = ()) -> tuple[subprocess.Popen[bytes], socket.socket]:
    """Start ``module`` in a process of its own (after ``prefix``: ``ip netns exec NS``), and
    return it with our end of its pair, non-blocking."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        proc = subprocess.Popen(
            [*prefix, sys.executable, "-m", module, json.dumps(cfg), str(theirs.fileno())],
            pass_fds=(theirs.fileno(),), cwd=ROOT)
    except BaseException:
        ours.close()
        raise
    finally:
        theirs.close()
    ours.setblocking(False)
    return proc, ours


def received(pair: socket.socket) -> tuple[list[tuple[bytes, bytes]], bool]:
    """The messages waiting on ``pair`` as (kind, body), and whether the process has ended."""
    out: list[tuple[bytes, bytes]] = []
    while True:
        try:
            msg = pair.recv(65536)
        except BlockingIOError:
            return out, False
        except OSError:
            msg = b""
        if not msg:
            return out, True
        out.append((msg[:1], msg[1:]))


def stop(proc: subprocess.Popen[bytes] | None, pair: socket.socket | None,
         release: bool = True) -> None:
    """End the child (blocking, at most a few seconds). With ``release`` it is asked to quit
    (its controller releases the AR first) and killed only if it has not within 3 s; without,
    it is killed at once, like a device switched off."""
    if proc is not None and not release:
        proc.kill()
    if pair is not None:
        if release:
            with contextlib.suppress(OSError):
                pair.send(b"Q")
        pair.close()
    if proc is not None:
        try:
            proc.wait(3.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main(serve: Callable[[dict[str, Any], socket.socket], None]) -> None:
    """The child's entry: ``serve(config, pair)`` until the parent closes its end."""
    cfg = json.loads(sys.argv[1])
    pair = socket.socket(fileno=int(sys.argv[2]))
    try:
        serve(cfg, pair)
    except (BrokenPipeError, ConnectionResetError):
        pass
    finally:
        os._exit(0)
