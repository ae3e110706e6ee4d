"""Image archive: NOK frames always, OK frames 1 in N, a quota evicting the oldest OK frames first.

Frames wait in memory until they are encoded (PNG) and written. So that a
trigger storm can neither grow that backlog without bound nor keep a core busy encoding, a
trigger's frames are only planned while few are waiting: OK frames when none are, NOK frames
while fewer than ``max_pending`` triggers' are. What is not planned is counted
(``skipped_ok``, ``skipped_nok``, in the station's status); the record then lists no images.

Measurement records are never deleted here: eviction removes a frame's file and marks its row,
so results outlive their images. The pipeline calls :meth:`ImageArchive.plan` before writing the
record (the refs go into the record) and :meth:`ImageArchive.write` after the PLC has its result,
off the trigger's critical path.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np

from server.errors import InvalidInputError, NotFoundError
from server.store.archive import ImageInfo, ImageRepository
from server.store.schemas import ImageRef


class ImageArchive:
    """Frames as PNG files under ``root``; their rows in the store's ``images`` table."""

    def __init__(self, root: Path, repo: ImageRepository, ok_every: int, quota_bytes: int,
                 max_pending: int = 8) -> None:
        if ok_every < 1:
            raise ValueError(f"ok_every must be >= 1, got {ok_every}")
        if quota_bytes <= 0:
            raise ValueError(f"quota_bytes must be > 0, got {quota_bytes}")
        self.root = Path(root)
        self.repo = repo
        self.ok_every = ok_every
        self.quota_bytes = quota_bytes
        # The trigger thread plans under _lock, so it is never held across I/O; the byte tally
        # and eviction read and write the database under _disk_lock (a frozen database then
        # holds the archive thread, never a trigger).
        self._lock = threading.Lock()
        self._disk_lock = threading.Lock()
        self.max_pending = max_pending
        self._ok_seen = 0
        self._pending = 0  # triggers whose frames are planned and not yet written or released
        self.skipped_ok = 0  # OK triggers due for the archive whose frames were not kept
        self.skipped_nok = 0
        self._stored: int | None = None  # bytes on disk, read from the store on first use

    def plan(
        self,
        station: str,
        trigger_id: int,
        triggered_at: datetime,
        ok: bool,
        cameras: Sequence[tuple[int, str]],
    ) -> list[ImageRef]:
        """Which frames of this trigger to keep (``[]`` for an OK trigger outside the 1 in N,
        or when too many triggers' frames wait to be written). Planned frames are then
        written (:meth:`write`) or given up (:meth:`release`): either ends their wait."""
        if not cameras:
            return []
        with self._lock:
            if ok:
                self._ok_seen += 1
                # The first OK frame is kept, then every N-th: a fresh archive is never empty.
                if (self._ok_seen - 1) % self.ok_every:
                    return []
                if self._pending:
                    self.skipped_ok += 1
                    return []
            elif self._pending >= self.max_pending:
                self.skipped_nok += 1
                return []
            self._pending += 1
        stamp = triggered_at.strftime("%Y%m%dT%H%M%S%fZ")
        day = triggered_at.strftime("%Y-%m-%d")
        return [
            ImageRef(
                view=view,
                camera_id=cam,
                path=f"{day}/{station}-{trigger_id}-{stamp}-v{view}-{cam}.png",
            )
            for view, cam in cameras
        ]

    def write(
        self,
        measurement_id: int,
        refs: Sequence[ImageRef],
        ok: bool,
        frames: Mapping[tuple[int, str], np.ndarray],
    ) -> list[ImageInfo]:
        """Write the planned frames (keyed by (view, camera_id)), then enforce the quota."""
        try:
            return self._write(measurement_id, refs, ok, frames)
        finally:
            if refs:
                self.release()

    def release(self) -> None:
        """One trigger's planned frames are written or given up: they wait no more."""
        with self._lock:
            self._pending = max(0, self._pending - 1)

    def status(self) -> dict[str, int]:
        with self._lock:
            return {"pending": self._pending, "skipped_ok": self.skipped_ok,
                    "skipped_nok": self.skipped_nok}

    def _write(self, measurement_id: int, refs: Sequence[ImageRef], ok: bool,
               frames: Mapping[tuple[int, str], np.ndarray]) -> list[ImageInfo]:
        written = []
        with self._disk_lock:
            self._current()  # read the baseline before adding rows, so nothing counts twice
        for ref in refs:
            frame = frames.get((ref.view, ref.camera_id))
            if frame is None:
                raise InvalidInputError(f"no frame for view {ref.view} camera {ref.camera_id!r}")
            path = self.resolve(ref.path)
            path.parent.mkdir(parents=True, exist_ok=True)
            good, buf = cv2.imencode(".png", np.ascontiguousarray(frame))
            if not good:
                raise InvalidInputError(
                    f"camera {ref.camera_id!r}: frame of shape {frame.shape} "
                    f"dtype {frame.dtype} cannot be encoded as PNG"
                )
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(buf.tobytes())
            os.replace(tmp, path)  # readers never see half a file
            written.append(
                self.repo.add(measurement_id, ref.view, ref.camera_id, ref.path, len(buf), ok)
            )
            with self._disk_lock:
                self._stored = self._current() + len(buf)  # baseline read above
        self.enforce_quota()
        return written

    def enforce_quota(self) -> list[ImageInfo]:
        """Delete frames, OK ones first and oldest first, until the archive fits its quota."""
        evicted: list[ImageInfo] = []
        with self._disk_lock:
            while self._current() > self.quota_bytes:
                batch = self.repo.eviction_order(limit=64)
                if not batch:
                    break
                chosen = []
                for info in batch:
                    if self._current() <= self.quota_bytes:
                        break
                    self.resolve(info.path).unlink(missing_ok=True)
                    self._stored = self._current() - info.bytes
                    chosen.append(info)
                self.repo.mark_evicted([i.id for i in chosen])
                evicted.extend(chosen)
        return evicted

    def stored_bytes(self) -> int:
        with self._disk_lock:
            return self._current()

    def resolve(self, rel: str) -> Path:
        """Absolute path of an archived frame; refuses paths that leave the archive."""
        path = (self.root / rel).resolve()
        if not path.is_relative_to(self.root.resolve()):
            raise NotFoundError(f"image path {rel!r} is outside the archive")
        return path

    def _current(self) -> int:
        if self._stored is None:
            self._stored = self.repo.stored_bytes()
        return self._stored
