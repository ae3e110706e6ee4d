"""Image archive: NOK frames always, OK frames 1 in N, quota evicts oldest OK frames first."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from records import T0, make_record

from mvpose_core.reasons import Reason
from server.errors import NotFoundError
from server.images import ImageArchive
from server.store import Store, open_store
from server.store.schemas import MeasurementFilter

CAMS = [(1, "cam1"), (1, "cam2")]


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    s = open_store(f"sqlite:///{tmp_path / 'db.sqlite'}", "station1")
    yield s
    s.close()


def _frames(rng: np.random.Generator) -> dict[tuple[int, str], np.ndarray]:
    # Noise does not compress: every PNG is about 64*64 bytes plus headers.
    return {key: rng.integers(0, 256, (64, 64), dtype=np.uint8) for key in CAMS}


def _trigger(store: Store, archive: ImageArchive, rng: np.random.Generator, i: int, ok: bool
             ) -> tuple[int, list]:
    when = T0.replace(second=i % 60, minute=i // 60)
    refs = archive.plan("station1", i, when, ok, CAMS)
    reason = Reason.OK if ok else Reason.MARKS_MISSING
    stored = store.measurements.insert(
        make_record(rng, trigger_id=i, reason=reason, triggered_at=when, images=refs))
    frames = _frames(rng)
    if refs:
        archive.write(stored.id, refs, ok, frames)
    return stored.id, [(r, frames[(r.view, r.camera_id)]) for r in refs]


def _planned(archive: ImageArchive, i: int, ok: bool) -> bool:
    """Plan a trigger's frames and, as the station does once they are written, release them."""
    refs = archive.plan("station1", i, T0, ok, CAMS)
    if refs:
        archive.release()
    return bool(refs)


def test_nok_always_ok_one_in_n(store: Store, tmp_path: Path) -> None:
    archive = ImageArchive(tmp_path / "img", store.images, ok_every=3, quota_bytes=10**9)
    kept_ok = [_planned(archive, i, True) for i in range(7)]
    assert kept_ok == [True, False, False, True, False, False, True]
    assert all(_planned(archive, 100 + i, False) for i in range(5))
    assert archive.status() == {"pending": 0, "skipped_ok": 0, "skipped_nok": 0}


def test_frames_waiting_to_be_written_bound_what_is_planned(store: Store, tmp_path: Path) -> None:
    """A trigger storm: OK frames are only planned when none wait to be written, NOK frames
    while fewer than max_pending triggers' do; what is skipped is counted, and a write or a
    release ends a trigger's wait."""
    archive = ImageArchive(tmp_path / "img", store.images, ok_every=1, quota_bytes=10**9,
                           max_pending=3)
    first = archive.plan("station1", 1, T0, True, CAMS)
    assert first and not archive.plan("station1", 2, T0, True, CAMS)
    assert [bool(archive.plan("station1", i, T0, False, CAMS)) for i in (3, 4, 5)] == [
        True, True, False]
    assert archive.status() == {"pending": 3, "skipped_ok": 1, "skipped_nok": 1}
    stored = store.measurements.insert(make_record(np.random.default_rng(1), trigger_id=1,
                                                   triggered_at=T0, images=first))
    archive.write(stored.id, first, True, _frames(np.random.default_rng(2)))
    archive.release()
    assert archive.status()["pending"] == 1
    assert not archive.plan("station1", 6, T0, True, CAMS)  # one NOK still waits
    archive.release()
    assert archive.plan("station1", 7, T0, True, CAMS)
    assert archive.status() == {"pending": 1, "skipped_ok": 2, "skipped_nok": 1}


def test_frames_are_written_losslessly_and_listed(store: Store, tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    archive = ImageArchive(tmp_path / "img", store.images, ok_every=1, quota_bytes=10**9)
    mid, written = _trigger(store, archive, rng, 1, ok=False)
    assert len(written) == 2
    for ref, frame in written:
        back = cv2.imread(str(archive.resolve(ref.path)), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(back, frame)
    rows = store.images.for_measurement(mid)
    assert {(r.view, r.camera_id) for r in rows} == set(CAMS)
    assert archive.stored_bytes() == sum(r.bytes for r in rows) > 0


def test_quota_evicts_oldest_ok_first_and_keeps_every_record(store: Store, tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    probe = ImageArchive(tmp_path / "probe", store.images, ok_every=1, quota_bytes=10**9)
    one_png = len(cv2.imencode(".png", _frames(rng)[CAMS[0]])[1])
    archive = ImageArchive(tmp_path / "img", store.images, ok_every=1,
                           quota_bytes=int(one_png * 2 * 5.5))  # room for ~5 triggers
    assert probe.stored_bytes() == 0
    kinds = [True, False, True, True, False, True, True, False, True, True]  # OK/NOK per trigger
    triggers = [_trigger(store, archive, rng, i, ok) for i, ok in enumerate(kinds)]
    assert archive.stored_bytes() <= archive.quota_bytes

    rows = [r for mid, _ in triggers for r in store.images.for_measurement(mid)]
    for r in rows:  # the row says what the disk says
        assert (r.evicted_at is None) == archive.resolve(r.path).exists()
    evicted = [r for r in rows if r.evicted_at is not None]
    kept_ok = [r for r in rows if r.ok and r.evicted_at is None]
    assert evicted, "the quota should have forced evictions"
    # only OK frames went (NOK ones stay while any OK frame is left), and the oldest ones
    assert all(r.ok for r in evicted) and kept_ok
    assert max(r.id for r in evicted) < min(r.id for r in kept_ok)
    # results outlive images: every record is still there and the chain is intact
    assert store.measurements.count(MeasurementFilter()) == len(kinds)
    assert store.measurements.verify_chain().ok

    # a restarted archive reads the bytes on disk from the store
    again = ImageArchive(tmp_path / "img", store.images, 1, archive.quota_bytes)
    assert again.stored_bytes() == archive.stored_bytes()


def test_when_only_nok_frames_remain_the_oldest_nok_go(store: Store, tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    one_png = len(cv2.imencode(".png", _frames(rng)[CAMS[0]])[1])
    archive = ImageArchive(tmp_path / "img", store.images, ok_every=1,
                           quota_bytes=int(one_png * 2 * 2.5))
    triggers = [_trigger(store, archive, rng, i, ok=False) for i in range(4)]
    alive = [all(archive.resolve(r.path).exists() for r, _ in refs) for _, refs in triggers]
    assert alive == [False, False, True, True]


def test_paths_cannot_leave_the_archive(store: Store, tmp_path: Path) -> None:
    archive = ImageArchive(tmp_path / "img", store.images, ok_every=1, quota_bytes=10)
    with pytest.raises(NotFoundError, match="outside the archive"):
        archive.resolve("../db.sqlite")
    with pytest.raises(ValueError, match="ok_every"):
        ImageArchive(tmp_path, store.images, ok_every=0, quota_bytes=10)
