"""The station's own data folder read offline: its store, and the frames its image archive kept.

``mvpose measure --from-archive`` and ``mvpose replay`` both read a station's records and their
archived frames (NOK always, OK 1 in ``MVPOSE_IMAGES_OK_EVERY``) through here; nothing is written
to the store.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from drivers.cameras import DriverError, Frame
from drivers.cameras.files import read_image
from server.cli import CliError
from server.store import Store, open_store
from server.store.schemas import StoredMeasurement


def when(text: str) -> datetime:
    """An ISO time from the command line (UTC unless it names its zone)."""
    t = datetime.fromisoformat(text)
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def open_data_dir(data_dir: Path, database_url: str | None, station: str) -> Store:
    """The store of a station's data folder (``<data_dir>/mvpose.db``, or ``database_url``)."""
    url = database_url or f"sqlite:///{(data_dir / 'mvpose.db').as_posix()}"
    if database_url is None and not (data_dir / "mvpose.db").is_file():
        raise CliError(f"{data_dir}: no store (mvpose.db); give the station's data folder or "
                       "--database-url")
    return open_store(url, station)


def frames_of(store: Store, images: Path, m: StoredMeasurement) -> dict[tuple[int, str],
                                                                        Frame | DriverError]:
    """The archived frames of a measurement (a frame evicted or missing: that camera fails)."""
    out: dict[tuple[int, str], Frame | DriverError] = {}
    root = images.resolve()
    for n, info in enumerate(store.images.for_measurement(m.id)):
        path = (root / info.path).resolve()
        if info.evicted_at is not None or not path.is_relative_to(root) or not path.is_file():
            why = "evicted from the archive" if info.evicted_at is not None else "missing"
            out[(info.view, info.camera_id)] = DriverError(
                f"camera {info.camera_id!r}: archived frame {info.path!r} is {why}")
            continue
        try:
            out[(info.view, info.camera_id)] = Frame(info.camera_id,
                                                     read_image(path, info.camera_id), n,
                                                     float("nan"), float("nan"))
        except DriverError as err:
            out[(info.view, info.camera_id)] = err
    return out


def result_id_ranges(text: str) -> list[tuple[int, int]]:
    """``--result-ids``: ``12``, ``12-40``, ``3,5,9-11`` as inclusive (first, last) ranges."""
    ranges = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        first, sep, last = part.partition("-")
        try:
            lo = int(first)
            hi = int(last) if sep else lo
        except ValueError:
            raise CliError(f"--result-ids: expected ids or ranges like 12-40, comma-separated; "
                           f"got {part!r}") from None
        if hi < lo:
            raise CliError(f"--result-ids: range {part!r} runs backwards")
        ranges.append((lo, hi))
    if not ranges:
        raise CliError(f"--result-ids: no ids in {text!r}")
    return ranges
