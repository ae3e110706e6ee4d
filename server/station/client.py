"""The API process's handle on the station process: the control channel's client.

Every call opens a connection, sends one request and reads one answer (a Unix socket on the
same machine: well under a millisecond), so a restarted station is reached again without any
reconnect logic. A station that does not answer is :class:`StationDownError`, which the API maps
to 503 and readiness reports as ``station: false``.
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from server.errors import ConflictError, InvalidInputError, NotFoundError, NotReadyError


class StationDownError(NotReadyError):
    """The station process does not answer on its control channel."""


_KINDS: dict[str, type[Exception]] = {
    "not_found": NotFoundError, "invalid": InvalidInputError, "conflict": ConflictError,
    "busy": ConflictError,
}


class StationClient:
    """Blocking calls to the station's control channel (from FastAPI's worker threads)."""

    def __init__(self, path: Path, timeout_s: float = 5.0, status_max_age_s: float = 0.25) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s
        # MES clients poll the status many times a second; each call would cost the station
        # process a request on its loop, beside the trigger thread (bench station: 0.27 -> 0.34
        # cores at 200 REST requests/s). One answer serves every request for this long.
        self.status_max_age_s = status_max_age_s
        self._status: tuple[float, dict[str, Any]] | None = None
        self._status_lock = threading.Lock()

    def call(self, op: str, timeout_s: float | None = None, **args: Any) -> Any:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
                sock.settimeout(timeout)
                sock.connect(str(self.path))
                sock.sendall(json.dumps({"id": 1, "op": op, "args": args}).encode() + b"\n")
                data = b""
                while not data.endswith(b"\n"):
                    chunk = sock.recv(1 << 20)
                    if not chunk:
                        break
                    data += chunk
        except (FileNotFoundError, ConnectionRefusedError) as err:
            raise StationDownError(f"the station process is not running ({err.strerror})") \
                from None
        except TimeoutError:
            raise StationDownError(f"the station process did not answer {op!r} within "
                                   f"{timeout:g} s") from None
        except OSError as err:
            raise StationDownError(f"the station process is not reachable: {err}") from None
        if not data:
            raise StationDownError("the station process closed the control channel")
        answer = json.loads(data)
        if answer.get("ok"):
            return answer.get("result")
        error = answer.get("error") or {}
        kind, message = error.get("kind", "internal"), error.get("message", "")
        exc = _KINDS.get(kind)
        if exc is None:
            raise RuntimeError(f"the station failed: {message}")
        raise exc(message)

    # ------------------------------------------------------------------ what the API uses
    def status(self) -> dict[str, Any]:
        """The station's status, at most ``status_max_age_s`` old."""
        with self._status_lock:  # one caller asks the station; the others wait for its answer
            now = time.monotonic()
            if self._status is not None and now - self._status[0] < self.status_max_age_s:
                return self._status[1]
            result: dict[str, Any] = self.call("status")
            self._status = (time.monotonic(), result)
            return result

    def readiness(self) -> Mapping[str, bool]:
        try:
            parts: dict[str, bool] = self.call("readiness", timeout_s=2.0)
        except StationDownError:
            return {"station": False}
        return {"station": True, **parts}

    def trigger(self, part_id: str | None = None, view_index: int = 0,
                trigger_id: int | None = None) -> dict[str, Any]:
        result: dict[str, Any] = self.call("trigger", timeout_s=35.0, part_id=part_id,
                                           view=view_index, trigger_id=trigger_id)
        return result

    def arm_teach(self, by: str) -> dict[str, Any]:
        result: dict[str, Any] = self.call("arm_teach", by=by)
        return result

    def teach_from_measurement(self, measurement_id: int, by: str) -> dict[str, Any]:
        result: dict[str, Any] = self.call("teach", timeout_s=35.0,
                                           measurement_id=measurement_id, by=by)
        return result

    def activate_recipe(self, name: str, version: int | None, by: str) -> dict[str, Any]:
        result: dict[str, Any] = self.call("activate_recipe", timeout_s=35.0, name=name,
                                           version=version, by=by)
        return result

    def metrics_text(self) -> str:
        """The station process's Prometheus text (its counters and histograms)."""
        result: dict[str, Any] = self.call("metrics", timeout_s=2.0)
        return str(result["text"])

    def move_part(self, offset: list[float]) -> dict[str, Any]:
        """Rehearsal on simulated cameras: the part at ``offset`` from the active reference."""
        result: dict[str, Any] = self.call("move_part", timeout_s=35.0, offset=offset)
        return result

    def reload_recipes(self) -> None:
        with contextlib.suppress(StationDownError):
            self.call("reload_recipes", timeout_s=35.0)
