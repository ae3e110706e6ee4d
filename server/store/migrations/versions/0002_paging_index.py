"""Index (station, id) so newest-first pages walk the index instead of sorting the station.

Without it SQLite picked the (station, part_id) index and sorted every record of the station
for each page: a page of 50 cost 5 ms at 1,000 records and grew linearly from there.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21
"""

from __future__ import annotations

from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_measurements_station_id", "measurements", ["station", "id"])


def downgrade() -> None:
    op.drop_index("ix_measurements_station_id", table_name="measurements")
