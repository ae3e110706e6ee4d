"""SQLite specifics: WAL and synchronous level are set; a committed record survives a crash."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import sqlalchemy as sa

from server.store import open_store
from server.store.schemas import MeasurementFilter

HERE = Path(__file__).parent


def test_wal_and_synchronous_full_on_every_connection(tmp_path: Path) -> None:
    store = open_store(f"sqlite:///{tmp_path / 's.db'}", "station1", sqlite_synchronous="FULL")
    try:
        with store.engine.connect() as conn:
            assert conn.execute(sa.text("PRAGMA journal_mode")).scalar_one() == "wal"
            assert conn.execute(sa.text("PRAGMA synchronous")).scalar_one() == 2  # FULL
            assert conn.execute(sa.text("PRAGMA foreign_keys")).scalar_one() == 1
    finally:
        store.close()
    assert (tmp_path / "s.db-wal").exists() or (tmp_path / "s.db").exists()


def test_a_record_committed_before_a_crash_is_there_after_it(tmp_path: Path) -> None:
    """The writer process dies right after insert returns (no close, no shutdown)."""
    url = f"sqlite:///{tmp_path / 'crash.db'}"
    code = textwrap.dedent(f"""
        import os, sys
        import numpy as np
        sys.path.insert(0, {str(HERE)!r})
        from records import make_record
        from server.store import open_store
        store = open_store({url!r}, "station1")
        stored = store.measurements.insert(make_record(np.random.default_rng(1), trigger_id=42))
        print(stored.hash, flush=True)
        os._exit(0)  # as abrupt as a kill: no pool cleanup, no WAL checkpoint
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, cwd=HERE.parent.parent)
    written_hash = out.stdout.strip().splitlines()[-1]
    store = open_store(url, "station1")
    try:
        items = list(store.measurements.iterate(MeasurementFilter()))
        assert [m.hash for m in items] == [written_hash]
        assert items[0].record.trigger_id == 42
        assert store.measurements.verify_chain().ok
    finally:
        store.close()
    assert np.isfinite(items[0].record.offset.values).all()
