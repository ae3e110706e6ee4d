"""PostgreSQL: refuse TRUNCATE of measurements too (row triggers do not fire on TRUNCATE).

SQLite has no TRUNCATE: its DELETE without WHERE fires the row trigger of 0001.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-21
"""

from __future__ import annotations

from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute(
            "CREATE TRIGGER measurements_no_truncate BEFORE TRUNCATE ON measurements "
            "FOR EACH STATEMENT EXECUTE FUNCTION mvpose_append_only()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("DROP TRIGGER IF EXISTS measurements_no_truncate ON measurements")
